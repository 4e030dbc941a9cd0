"""``vsrd-mi bench residual-scenes``: how often the adaptive sampler misses the 0.01 label bound with
the residual field, per random scene, against the converged reference.

The integrator tests' random scenes (:func:`~vsrd_mi.bench.scenes.random_scene`,
:func:`~vsrd_mi.bench.scenes.training_rays`; 2 boxes for even seeds, 3 for odd ones, touching
pairs, occlusions and grazing rays) with the residual field at its initialisation, s = 10, 256
rays each: per scene the largest and the 99th-percentile label error of the adaptive sampler
against the converged reference (:func:`~vsrd_mi.bench.measure.reference_labels`: a fine
uniform grid plus every box's deepest point), and the ray of the largest. Summary per seed
range: scenes with a label above 0.01, the worst, the mean of the scenes' maxima and 99th
percentiles. Seeds 40-299 were examined while the moved samples and kink minima were built,
300-559 only measured. Labels only, no timing.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import drjit as dr

from .measure import reference_labels, write_results
from .scenes import random_scene, silhouette_integrator, to_rays, training_rays

#: The bound on the adaptive sampler's label error, the schedule and the rays per scene.
LABEL_BOUND = 0.01
SHARPNESS = 10.0
RAYS = 256


def scene_errors(seed: int) -> dict:
    """The adaptive sampler's largest and 99th-percentile label error on one random scene."""
    n_inst = 2 + seed % 2
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n_inst)
    rays = to_rays(*training_rays(rng, scene, RAYS))
    kw = dict(sharpness=SHARPNESS, temperature=1.0 / SHARPNESS, residual=True)
    with dr.suspend_grad():
        ref = reference_labels(silhouette_integrator(scene, sampling="dense", **kw), scene, rays, SHARPNESS)[:n_inst]
        labels = silhouette_integrator(scene, **kw).render_rays(*rays)[:n_inst]
    err = np.abs(np.stack([np.array(x) for x in labels]) - np.stack([np.array(x) for x in ref])).max(axis=0)
    return {"seed": seed, "instances": n_inst, "max": float(err.max()), "p99": float(np.quantile(err, 0.99)),
            "worst_ray": int(err.argmax())}


def summarise(rows: list[dict]) -> dict:
    maxima, p99 = np.array([r["max"] for r in rows]), np.array([r["p99"] for r in rows])
    return {"scenes": len(rows), "above_bound": int((maxima > LABEL_BOUND).sum()), "bound": LABEL_BOUND,
            "worst": float(maxima.max()), "worst_seed": rows[int(maxima.argmax())]["seed"],
            "mean_max": float(maxima.mean()), "mean_p99": float(p99.mean())}


def register(subparsers) -> None:
    p = subparsers.add_parser("residual-scenes", help="vsrd_silhouette with the residual field: label error per "
                                                      "random scene against the converged reference",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ranges", type=int, nargs="+", default=[40, 300, 300, 560], metavar="SEED",
                   help="pairs FIRST END of seed ranges (FIRST..END-1), summarised each")
    p.add_argument("--out", type=Path, default=Path("benchmarks/residual_scenes.json"))
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    if len(args.ranges) % 2:
        raise SystemExit("--ranges takes pairs FIRST END")
    start = time.perf_counter()
    ranges = []
    for first, end in zip(args.ranges[0::2], args.ranges[1::2]):
        rows = [scene_errors(seed) for seed in range(first, end)]
        ranges.append({"seeds": [first, end], "summary": summarise(rows), "scenes": rows})
        print(f"seeds {first}..{end - 1}: {ranges[-1]['summary']}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_results(args.out, __doc__, time.perf_counter() - start, sharpness=SHARPNESS, rays=RAYS, ranges=ranges)
    print(f"wrote {args.out}")
    return 0
