"""Where must the adaptive sampler put its samples with the residual field? Labels vs the reference and step time per sampling setting.

On the integrator benchmark's residual scenes (``vsrd-mi bench integrator``: same seeds, same
rays, s = 10), for each setting (integrator options; :data:`SETTINGS`): the adaptive sampler's
soft labels against the brute-force reference (:func:`vsrd_mi.bench.integrator.reference_chunk`,
5 mm grid plus every box's deepest point; computed once per scene) on the first 512 rays: max,
99th percentile and the number of rays above the issue's 0.01; and the forward + backward step
time at 6 boxes / 16k rays, every setting timed in turn in one loop (this machine is noisy:
compare the ratios). For the worst rays of the first setting it also lists the local minima of
the instance SDF ``B + R`` along the ray inside its box's culling margin (a 1 mm scan): the
integral's discrete opacity telescopes over each monotone descent, so every local maximum and
minimum of ``B + R`` is a place a sample must sit. The settings: uniform tail samples (12-32
per band, samples left where the band formula puts them, ``residual_tail_scan = 0``), then the
default 12 with band and tail samples moved to the extrema a detached scan finds (1-3 scan
points per sample), the default with a coarser residual grid, with the grid always filled by
the MLP (no per-instance lattice, ``residual_lattice = 0``: the timing differs, the 512
accuracy rays never use the lattice) and without the grid (every scan point and sample
evaluates the residual; ``residual_grid``), and the default without the sparse AD graph.

Usage::

    python benchmarks/residual_tails.py --out benchmarks/residual_tails.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from common import side_by_side_steps, write_results
import vsrd_mi  # noqa: F401  (sets the variant, registers the plugins)
from vsrd_mi.bench import integrator as bench

#: Scan step (m) along a worst ray when counting the local minima of ``B + R``.
SCAN_STEP = 1e-3
#: Worst rays per scene whose ``B + R`` profile is reported.
WORST = 3
#: (name, integrator options): the sampling settings compared.
SETTINGS = (
    ("tail 12, not moved", {"residual_tail": 12, "residual_tail_scan": 0}),
    ("tail 16, not moved", {"residual_tail": 16, "residual_tail_scan": 0}),
    ("tail 24, not moved", {"residual_tail": 24, "residual_tail_scan": 0}),
    ("tail 32, not moved", {"residual_tail": 32, "residual_tail_scan": 0}),
    ("moved, scan 1", {"residual_tail_scan": 1}),
    ("moved, scan 2", {"residual_tail_scan": 2}),
    ("default (moved, scan 3)", {}),
    ("default, residual grid 0.75 rad", {"residual_grid": 0.75}),
    ("default, grid filled by the MLP (no residual lattice)", {"residual_lattice": 0}),
    ("default, exact residual (no grid)", {"residual_grid": 0}),
    ("default, full AD graph", {"residual_sparse_gradients": False}),
)


def reference_labels(data: bench.CaseData, n: int, cfg: bench.BenchConfig) -> np.ndarray:
    """The brute-force reference's labels (instances, rays) of the first ``n`` rays."""
    it = bench.load_integrator(data.boxes, "dense", True, cfg)
    return bench.labels_and_gradient(it, bench.reference_chunks(it, data, n, cfg))[0]


def adaptive(data: bench.CaseData, options: dict, cfg: bench.BenchConfig):
    return bench.load_integrator(data.boxes, "adaptive", True, cfg, **options)


def adaptive_labels(data: bench.CaseData, options: dict, n: int, cfg: bench.BenchConfig) -> np.ndarray:
    it = adaptive(data, options, cfg)
    batch = data.batch(n)
    with dr.suspend_grad():
        return np.stack([np.array(x) for x in it.render_rays(batch.o, batch.d, batch.time)[:it.field.n]])


def local_minima(data: bench.CaseData, ray: int, inst: int, cfg: bench.BenchConfig) -> list:
    """``(t, B + R)`` at the local minima of instance ``inst``'s SDF along ``ray``, where it lies
    within the culling margin (a :data:`SCAN_STEP` scan)."""
    it = adaptive(data, {}, cfg)
    margin = float(np.array(it._cull_margin())[0])
    far = float(bench.reference_samples(data.boxes, cfg)[0])
    t = np.arange(0.0, far, SCAN_STEP, dtype=np.float32)
    o, d = data.o[ray], data.d[ray]
    p = mi.Point3f(*[mi.Float(o[i] + t * d[i]) for i in range(3)])
    with dr.suspend_grad():
        f = np.array(it.field.instance_sdfs(it.field.decode(), p, dr.full(mi.Float, float(data.t[ray]), len(t)),
                                            it.field.residual_weights(), reach=it._residual_reach())[inst])
    idx = [i for i in range(1, len(f) - 1) if f[i] < f[i - 1] and f[i] <= f[i + 1] and f[i] < margin]
    return [(round(float(t[i]), 3), round(float(f[i]), 4)) for i in idx]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/residual_tails.json"))
    ap.add_argument("--instances", type=int, nargs="+", default=[3, 6, 12])
    ap.add_argument("--timing-instances", type=int, default=6)
    ap.add_argument("--timing-rays", type=int, default=16384)
    ap.add_argument("--repeats", type=int, default=4)
    args = ap.parse_args()
    cfg = bench.BenchConfig()
    start = time.perf_counter()
    n = cfg.accuracy_rays
    rows = []
    for k in args.instances:
        data, _ = bench.case_data(cfg, k, True)
        ref = reference_labels(data, n, cfg)
        for name, options in SETTINGS:
            err = np.abs(adaptive_labels(data, options, n, cfg) - ref)
            per_ray = err.max(axis=0)
            worst = [int(r) for r in np.argsort(per_ray)[::-1][:WORST]]
            rows.append({"instances": k, "setting": name, "options": options, "max_abs": float(per_ray.max()),
                         "p99_abs": float(np.quantile(per_ray, 0.99)), "rays_above_0.01": int((per_ray > 0.01).sum()),
                         "worst": [{"ray": r, "error": float(per_ray[r]), "instance": int(err[:, r].argmax()),
                                    "local_minima": local_minima(data, r, int(err[:, r].argmax()), cfg)}
                                   for r in worst] if name == SETTINGS[0][0] else
                                  [{"ray": r, "error": float(per_ray[r])} for r in worst]})
            print(f"{k:2d} boxes, {name:26s}: max {rows[-1]['max_abs']:.4f} p99 {rows[-1]['p99_abs']:.4f} "
                  f"rays > 0.01: {rows[-1]['rays_above_0.01']}", flush=True)
    data, _ = bench.case_data(cfg, args.timing_instances, True)
    batch = data.batch(args.timing_rays)
    seconds = side_by_side_steps({name: bench.TimedIntegrator(adaptive(data, options, cfg), batch, cfg, seed=1)
                                  for name, options in SETTINGS}, args.repeats)
    base = float(np.median(seconds[SETTINGS[0][0]]))
    timing = [{"setting": name, "median_s": float(np.median(s)), "runs_s": s,
               "ratio_to_first": float(np.median(s)) / base} for name, s in seconds.items()]
    for t in timing:
        print(f"{t['setting']:26s}: {t['median_s']:.3f} s ({t['ratio_to_first']:.2f}x)")
    write_results(args.out, __doc__, time.perf_counter() - start, config={
        "sharpness": cfg.sharpness, "temperature": cfg.temperature, "accuracy_rays": n,
        "timing": {"instances": args.timing_instances, "rays": args.timing_rays, "repeats": args.repeats}},
        accuracy=rows, timing=timing)
    return 0


if __name__ == "__main__":
    sys.exit(main())
