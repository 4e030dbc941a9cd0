"""Parked or moving? The stereo initialisation's dynamic flag on every target instance.

A parked car labelled moving gets a velocity that the init regulariser then holds (weight
``init_dynamic``), and its location comes from a few frames moved by that velocity: on seed 4401
one such car ended 2.5 m too far (3D IoU 0.17). This script runs the velocity estimate
(:func:`vsrd_mi.init.attributes.estimate_velocity`) on the clouds of every target instance of the
six 4 + 2 sequences of ``mixed_sequences.py`` and of the bundled scene, under variants of
:class:`vsrd_mi.init.config.VelocityConfig` (which frame pairs, their weights) and of the
significance test (Student's t at the kept pairs' effective count, or the plain ``significance``
standard errors), and scores the flags and speeds against the ground truth (read only here).

Usage::

    python benchmarks/dynamic_flags.py --out benchmarks/dynamic_flags.json
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from common import BUNDLED, write_results
from mixed_sequences import N_DYNAMIC, N_STATIC, SEEDS
from vsrd_mi.bench.autolabel import BenchDataset, ensure_dataset
from vsrd_mi.data.kitti360 import Sequence, sequence_name
from vsrd_mi.data.selection import select_targets
from vsrd_mi.init.attributes import collect_clouds, estimate_velocity, is_dynamic
from vsrd_mi.init.config import InitConfig
from vsrd_mi.init.sequence import stereo_frames

#: name -> (VelocityConfig overrides, Student's t test at the effective pair count)
VARIANTS = {
    "2 neighbours, point weights, plain test": (dict(pair_neighbours=2, gap_weighted=False), False),
    "2 neighbours, point weights, t test": (dict(pair_neighbours=2, gap_weighted=False), True),
    "4 neighbours, point weights, t test": (dict(pair_neighbours=4, gap_weighted=False), True),
    "4 neighbours, gap^2 weights, plain test": (dict(pair_neighbours=4, gap_weighted=True), False),
    "default (4 neighbours, gap^2 weights, t test)": ({}, True),
}


def score_sequence(root: Path, cfg: InitConfig) -> list[dict]:
    """One row per (target, instance with a cloud): ground truth and every variant's flag / speed."""
    seq = Sequence(root, sequence_name(0))
    rate = cfg.velocity.frame_rate_hz
    rows = []
    for spec in select_targets(seq):
        clouds, _, truncated = collect_clouds(
            stereo_frames(seq, spec.target, spec.sources, spec.instance_ids, cfg), cfg)
        truth = {b.instance_id: b for b in seq.ground_truth(spec.target)}
        for iid, per_frame in sorted(clouds.items()):
            if iid not in truth:
                continue
            usable = {o: c for o, c in per_frame.items() if o not in truncated.get(iid, set())}
            gt = truth[iid]
            row = {"sequence": root.name, "target": spec.target, "instance": iid,
                   "gt_dynamic": bool(gt.dynamic), "gt_speed_mps": float(np.linalg.norm(gt.velocity) * rate),
                   "distance_m": float(np.linalg.norm(gt.centre))}
            for name, (overrides, t_test) in VARIANTS.items():
                vc = dataclasses.replace(cfg.velocity, **overrides)
                est = estimate_velocity(usable, vc)
                flag = is_dynamic(est.velocity, vc, est.standard_error,
                                  est.effective_pairs if t_test else float("inf"))
                row[name] = {"dynamic": bool(flag), "speed_mps": float(np.linalg.norm(est.velocity) * rate)}
            rows.append(row)
    return rows


def summarise(rows: list[dict]) -> dict:
    """Per variant: wrong flags (both ways), speed error of moving cars, apparent speed of parked ones."""
    moving = [r for r in rows if r["gt_dynamic"]]
    parked = [r for r in rows if not r["gt_dynamic"]]
    out = {}
    for name in VARIANTS:
        wrong = [r for r in rows if r[name]["dynamic"] != r["gt_dynamic"]]
        out[name] = {
            "wrong": len(wrong), "instances": len(rows),
            "parked_labelled_moving": sum(r[name]["dynamic"] for r in parked),
            "moving_labelled_parked": sum(not r[name]["dynamic"] for r in moving),
            "moving_speed_error_median_mps": float(np.median([abs(r[name]["speed_mps"] - r["gt_speed_mps"]) for r in moving])),
            "parked_apparent_speed_median_mps": float(np.median([r[name]["speed_mps"] for r in parked])),
            "parked_apparent_speed_p90_mps": float(np.percentile([r[name]["speed_mps"] for r in parked], 90)),
            "wrong_cases": [f"{r['sequence']} t{r['target']} {r['instance']} ({r['distance_m']:.0f} m)" for r in wrong],
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-dir", type=Path, default=Path("runs/bench-data"))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--no-bundled", action="store_true", help="leave the bundled scene out")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/dynamic_flags.json"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    roots = [ensure_dataset(args.data_dir, BenchDataset(f"mixed-{N_STATIC}-{N_DYNAMIC}", N_STATIC, N_DYNAMIC, s))
             for s in args.seeds]
    if not args.no_bundled:
        roots.append(BUNDLED)
    cfg = InitConfig()
    rows = []
    for root in roots:
        rows += score_sequence(root, cfg)
        print(f"{root.name}: {len(rows)} instances so far", flush=True)
    summary = summarise(rows)
    for name, s in summary.items():
        print(f"{name}: wrong {s['wrong']} of {s['instances']} (parked as moving {s['parked_labelled_moving']}, "
              f"moving as parked {s['moving_labelled_parked']}), moving speed error median "
              f"{s['moving_speed_error_median_mps']:.2f} m/s, parked apparent p90 {s['parked_apparent_speed_p90_mps']:.2f} m/s")
    write_results(args.out, __doc__, time.perf_counter() - t0, summary=summary, rows=rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
