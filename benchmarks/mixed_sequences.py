"""Issue 4's accuracy criterion on fresh sequences: 4 parked + 2 moving cars, default preset.

The criterion (mean 3D IoU >= 0.7 for parked, >= 0.6 for moving cars on a synthetic sequence
with 4+ parked and 2+ moving cars) was measured on the bundled scene only, one draw of car sizes
and placements. This script generates ``--seeds`` more such sequences with the data layer's
generator (seeds fixed here before any was run, not picked by result: 4401-4403 first, 4404-4406
added as fresh validation for the car profile, chosen on the first three), autolabels every target
frame of each with ``vsrd-mi autolabel`` (default preset, with its consensus of parked cars over
the sequence, or ``--set`` overrides) and evaluates
every labelled frame (the targets and their groups) with the evaluator, as the README's bundled
scene figures are. Finished targets are skipped on rerun.

Usage::

    python benchmarks/mixed_sequences.py --out benchmarks/mixed_sequences.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from common import write_results
from vsrd_mi.bench.autolabel import BenchDataset, ensure_dataset
from vsrd_mi.evaluate.sequence import evaluate_sequence

SEEDS = (4401, 4402, 4403, 4404, 4405, 4406)
N_STATIC, N_DYNAMIC = 4, 2


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-dir", type=Path, default=Path("runs/bench-data"))
    ap.add_argument("--work", type=Path, default=Path("runs/mixed-sequences"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/mixed_sequences.json"))
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    rows = []
    t0 = time.perf_counter()
    for seed in args.seeds:
        root = ensure_dataset(args.data_dir, BenchDataset(f"mixed-{N_STATIC}-{N_DYNAMIC}", N_STATIC, N_DYNAMIC, seed))
        out = args.work / root.name
        t = time.perf_counter()
        cmd = ["vsrd-mi", "autolabel", str(root), "--sequence", "0", "--out", str(out), "--no-progress"]
        for o in args.overrides:
            cmd += ["--set", o]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        ev = evaluate_sequence(out, root, 0)
        pairs = ev["pairs"]
        row = {"seed": seed, "sequence": root.name, "seconds": time.perf_counter() - t,
               "frames_evaluated": len(ev["frames"]),
               **{f"{g}_mean_iou_3d": pairs[g]["mean_iou_3d"] for g in ("static", "dynamic", "all")},
               **{f"{g}_pairs": pairs[g]["n_matched"] for g in ("static", "dynamic")},
               "size_error_m": pairs["all"]["size_error_m"], "yaw_error_deg": pairs["all"]["yaw_error_deg"]}
        rows.append(row)
        print(json.dumps(row), flush=True)
    summary = {g: float(np.mean([r[f"{g}_mean_iou_3d"] for r in rows])) for g in ("static", "dynamic", "all")}
    write_results(args.out, __doc__, time.perf_counter() - t0, overrides=args.overrides,
                  mean_over_sequences=summary, rows=rows)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
