"""Accuracy on a synthetic set: ``vsrd-mi bench validation [--set validation|development|development-traffic]``.

The sets of :mod:`vsrd_mi.synth.suites` (rounds of six hard streets: mixed classes parked every
way, angled and perpendicular bays, tight rows with occlusion, moving traffic, wide and tall
vehicles; the development set, one round, is for tuning, the validation set, three rounds, only
for reporting; ``development-traffic`` adds four development streets of moving traffic) are
generated once under ``--root`` (``--rounds N``: the first N rounds only) and autolabelled with
the default configuration (or ``--config`` / ``--set``): per sequence the ``--targets`` middle
target frames, in one ``vsrd-mi autolabel`` run each (so the
consensus of parked cars fuses over them), ``--jobs`` sequences at a time. Every labelled frame is
then evaluated (:mod:`vsrd_mi.evaluate`, the authors' mask protocol) and all sequences are pooled:

* mean 3D IoU of matched parked and moving cars, AP_3D / AOS, the share of cars without a box;
* heading accuracy of parked cars, the yaw error modulo 180 degrees of angled ones;
* signed length / width / height bias per vehicle class;
* by distance and by occlusion;
* by whether some view that labels a car sees its length (:mod:`vsrd_mi.evaluate.observability`),
  and the class biases over the cars whose length is seen (reported; the bound is on all);

and checked against issue 33's bounds (:data:`BOUNDS`). Writes ``benchmarks/<set>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..data.kitti360 import Sequence, sequence_name
from ..data.selection import select_targets
from ..evaluate.cli import bias_interval_table
from ..evaluate.sequence import EvalConfig, evaluate_frames, sequence_frames
from ..synth.suites import SET_SEEDS, select, suite, write_suite

#: Issue 33's bounds, each ``(result path, comparison, value)``; sizes are relative biases.
BOUNDS = {
    "parked mean 3D IoU >= 0.78": ("parked_iou", ">=", 0.78),
    "moving mean 3D IoU >= 0.72": ("moving_iou", ">=", 0.72),
    "parked heading right >= 90 %": ("parked_heading_accuracy", ">=", 0.90),
    "angled parked yaw error mod 180 <= 5 deg": ("angled_yaw_error_deg", "<=", 5.0),
    "|length bias| <= 5 % per class": ("worst_length_bias", "<=", 0.05),
    "|height bias| <= 5 % per class": ("worst_height_bias", "<=", 0.05),
    "cars without a box <= 5 %": ("missed_share", "<=", 0.05),
}


def middle_targets(root: Path, sequence: int, count: int) -> list[int]:
    """The ``count`` middle target frames of a sequence (all when ``count`` is 0 or more)."""
    targets = [s.target for s in select_targets(Sequence(root, sequence))]
    if count <= 0 or count >= len(targets):
        return targets
    lo = (len(targets) - count) // 2
    return targets[lo:lo + count]


def autolabel(root: Path, sequence: int, targets: list[int], out: Path, extra: list[str]) -> dict:
    """``vsrd-mi autolabel`` of ``targets`` (a frame range) in a fresh process; its wall time."""
    cmd = [sys.executable, "-m", "vsrd_mi", "autolabel", str(root), "--sequence", str(sequence), "--out", str(out),
           "--frames", f"{targets[0]}-{targets[-1]}", "--no-progress", *extra]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"autolabel of sequence {sequence} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return {"sequence": sequence, "targets": targets, "wall_seconds": time.perf_counter() - start}


def target_seconds(out: Path, sequence: int) -> list[float]:
    """Seconds of every target's optimisation run, from its ``boxes/*.json``."""
    folder = out / sequence_name(sequence) / "boxes"
    return [float(json.loads(p.read_text())["seconds"]) for p in sorted(folder.glob("*.json"))]


def headline(result: dict) -> dict:
    """The figures :data:`BOUNDS` checks, from a pooled :func:`evaluate_frames` result, and the
    worst class length bias over the cars whose length a view sees (reported, no bound)."""
    pairs, breakdown = result["pairs"], result["breakdown"]
    parking = breakdown.get("by_parking") or {}
    angled = parking.get("angled") or {}
    classes = breakdown.get("by_class") or {}

    def worst(extent: str, groups: dict) -> float | None:
        values = [abs(c["size_bias"][extent]["mean_rel"]) for c in groups.values()
                  if c and c.get("size_bias")]
        return max(values) if values else None

    return {"parked_iou": pairs["static"]["mean_iou_3d"], "moving_iou": pairs["dynamic"]["mean_iou_3d"],
            "parked_heading_accuracy": pairs["static"]["heading_accuracy"],
            "angled_yaw_error_deg": angled.get("yaw_error_deg"),
            "worst_length_bias": worst("length", classes), "worst_height_bias": worst("height", classes),
            "missed_share": pairs["all"]["missed_share"],
            "worst_length_bias_seen": worst("length", breakdown.get("by_class_length_seen") or {})}


def check(figures: dict) -> dict[str, bool | None]:
    """Each bound of :data:`BOUNDS` met (None where the figure is missing)."""
    out = {}
    for name, (key, op, bound) in BOUNDS.items():
        value = figures.get(key)
        out[name] = None if value is None else (value >= bound if op == ">=" else value <= bound)
    return out


def run(set_name: str, root: Path, work: Path, targets: int, jobs: int, extra: list[str],
        resume: bool = False, rounds: int | None = None) -> dict:
    """Generate (if needed), autolabel and evaluate a set, or its first ``rounds`` rounds (see
    the module docstring).

    The sequences' folders under ``work`` are removed first unless ``resume``: autolabel resumes
    the targets it finds done with the same configuration, and a code change that the
    configuration does not record would otherwise be measured on the earlier labels.
    """
    write_suite(root, set_name, rounds=rounds)
    members = select(suite(set_name), None, rounds)
    plans = [(m.sequence, middle_targets(root, m.sequence, targets)) for m in members]
    if not resume:
        for m in members:
            shutil.rmtree(work / sequence_name(m.sequence), ignore_errors=True)
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        runs = list(pool.map(lambda p: autolabel(root, p[0], p[1], work, extra), plans))
    config = EvalConfig(length_views=True)
    frames, per_sequence = [], {}
    for member, r in zip(members, runs):
        seq_frames, info = sequence_frames(work, root, member.sequence, None, config)
        frames += seq_frames
        ev = evaluate_frames(seq_frames, config)
        per_sequence[sequence_name(member.sequence)] = {
            "preset": member.scenario.name, "round": member.round, "seed": member.seed, **r,
            "frames": info["frames"],
            "target_seconds": target_seconds(work, member.sequence), "figures": headline(ev)}
    pooled = evaluate_frames(frames, config)
    figures = headline(pooled)
    seconds = [s for v in per_sequence.values() for s in v["target_seconds"]]
    return {"set": set_name, "root": str(root), "rounds": 1 + max(m.round for m in members),
            "targets_per_sequence": targets, "autolabel_args": extra,
            "figures": figures, "bounds": check(figures), "per_sequence": per_sequence,
            "seconds_per_target": {"mean": float(np.mean(seconds)), "median": float(np.median(seconds))},
            "pooled": pooled, "machine": {"cpus": os.cpu_count()}}


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("validation", help="accuracy on the synthetic validation (or development) set",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--set", dest="set_name", choices=sorted(SET_SEEDS), default="validation",
                   help="validation (report only), development (tune on it) or development-traffic "
                        "(four more development streets with moving traffic)")
    p.add_argument("--root", type=Path, help="where the set is generated (default runs/bench-data/<set>)")
    p.add_argument("--work", type=Path, help="autolabel output (default runs/bench-<set>)")
    p.add_argument("--rounds", type=positive_int, help="only the set's first ROUNDS rounds of streets, one street "
                   "per preset each (default: all; not bench autolabel's --rounds, its timed repetitions)")
    p.add_argument("--targets", type=int, default=4, help="middle target frames per sequence (0 = all)")
    p.add_argument("--jobs", type=int, default=1, help="sequences autolabelled at the same time")
    p.add_argument("--config", default="default", help="autolabel preset")
    p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                   help="autolabel --set override (repeatable)")
    p.add_argument("--json", type=Path, help="result file (default benchmarks/<set>.json)")
    p.add_argument("--resume", action="store_true",
                   help="keep the targets an earlier run of --work finished (default: label afresh)")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    root = args.root or Path("runs/bench-data") / args.set_name
    work = args.work or Path(f"runs/bench-{args.set_name}")
    extra = ["--config", args.config] + [a for o in args.option for a in ("--set", o)]
    result = run(args.set_name, root, work, args.targets, args.jobs, extra, args.resume, args.rounds)
    path = args.json or Path("benchmarks") / f"{args.set_name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"{args.set_name}: {len(result['per_sequence'])} streets ({result['rounds']} round(s)), "
          f"{args.targets or 'all'} target frames each")
    for name, ok in result["bounds"].items():
        key = BOUNDS[name][0]
        print(f"{'PASS' if ok else 'FAIL' if ok is not None else '  - '}  {name:42s} {result['figures'][key]}")
    breakdown = result["pooled"]["breakdown"]
    for key, title in (("by_class", "size bias by vehicle class, 95 % interval over cars:"),
                       ("by_length_view", "whether a view that labels the car sees its length:"),
                       ("by_class_length_seen", "by vehicle class, cars whose length a view sees:")):
        if breakdown.get(key):
            print(title)
            print("\n".join(bias_interval_table(breakdown[key])))
    print(f"seconds per target: mean {result['seconds_per_target']['mean']:.1f}; wrote {path}")
    return 0
