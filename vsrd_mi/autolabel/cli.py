"""``vsrd-mi autolabel``: every target frame of a sequence through :func:`.job.process_target`
(resumable, in-process or on Dask, :mod:`vsrd_mi.batch`), then the consensus of parked cars
(:mod:`.consensus`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..batch.cli import add_executor_arguments, executor_kwargs
from ..batch.runner import run_batch
from ..batch.tasks import TargetTask
from ..data.kitti360 import Sequence, sequence_name
from ..data.selection import SelectionConfig, select_targets
from ..errors import DataError
from ..optimise.config import PRESETS
from .consensus import apply_consensus
from .job import process_target


def _frame_range(text: str | None) -> list[int] | None:
    if not text:
        return None
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def _cmd_autolabel(args: argparse.Namespace) -> int:
    cfg = PRESETS[args.config]()
    try:  # argument errors before any dataset I/O
        cfg = cfg.with_overrides(args.set or [])
        where = executor_kwargs(args)
    except ValueError as exc:
        print(f"vsrd-mi autolabel: {exc}", file=sys.stderr)
        return 2
    cfg = cfg.replace(residual=cfg.residual and not args.no_residual,
                      velocity=cfg.velocity and not args.no_velocity, init=cfg.init and not args.no_init)
    if args.steps:
        cfg = cfg.replace(steps=args.steps, warmup_steps=min(cfg.warmup_steps, args.steps // 3))
    seq = Sequence(args.root, args.sequence)
    selection = SelectionConfig()
    specs = select_targets(seq, selection, frames=_frame_range(args.frames))
    if not specs:
        which = f"frames {args.frames} of " if args.frames else ""
        print(f"vsrd-mi autolabel: {seq.instance_dir}: no target frame in {which}{seq.name}: no frame has a car "
              f"mask of >= {selection.min_mask_area} px and box side >= {selection.min_box_side:g} px seen in "
              f">= {selection.min_sources} other frames; nothing to label", file=sys.stderr)
        return 1
    print(f"{seq.name}: {len(specs)} target frame(s)" + "".join(
        f"\n  target {s.target}: {len(s.sources)} sources" + (f" ({s.note})" if s.note else "") for s in specs))
    # the consensus is sequence-level: changing it must not rerun finished targets
    target_cfg = {k: v for k, v in cfg.to_dict().items() if k != "consensus"}
    tasks = [TargetTask(root=str(Path(args.root).resolve()), sequence=seq.name, frame=s.target,
                        output_dir=str(Path(args.out).resolve()),
                        config={**target_cfg, **({"vis": True} if args.vis else {})}, seed=args.seed)
             for s in specs]
    summary = run_batch(tasks, process_target, **where)
    print(f"done {summary.done}, skipped {summary.skipped}, failed {summary.failed} of {summary.total}")
    try:
        consensus = apply_consensus(Path(args.out) / seq.name, seq, cfg.consensus, cfg.heading)
    except (DataError, OSError) as exc:  # the targets' own labels stay as written
        print(f"vsrd-mi autolabel: consensus of parked cars skipped: {exc}", file=sys.stderr)
        return summary.exit_code()
    if consensus["enabled"]:
        print(f"consensus: {len(consensus['fused'])} parked car(s) fused over {len(consensus['targets'])} "
              f"target(s), {len(consensus['labels_rewritten'])} label file(s) rewritten"
              + "".join(f"\n  left out: {s}" for s in consensus["skipped"]))
    return summary.exit_code()


def register(subparsers) -> None:
    p = subparsers.add_parser("autolabel", help="optimise 3D boxes for the target frames of a sequence")
    p.add_argument("root", help="KITTI-360 root")
    p.add_argument("--sequence", required=True, type=sequence_name)
    p.add_argument("--out", required=True, help="output directory (labels under OUT/SEQ/)")
    p.add_argument("--frames", help="A-B: frames that may be targets (sources come from the whole sequence)")
    p.add_argument("--config", choices=sorted(PRESETS), default="default")
    p.add_argument("--steps", type=int, help="override the number of optimisation steps")
    p.add_argument("--no-residual", action="store_true",
                   help="no residual distance field (the default preset has none; --set residual=true "
                        "--set weights.silhouette=1 adds it)")
    p.add_argument("--no-velocity", action="store_true")
    p.add_argument("--no-init", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a configuration field, e.g. --set weights.init_dynamic=0.1 "
                        "--set lr.box=0.02 (repeatable; fields of vsrd_mi.optimise.config)")
    p.add_argument("--vis", action="store_true",
                   help="also write visual checks (projected boxes, masks, BEV, losses, meshes) "
                        "under OUT/SEQ/vis/<target>/")
    add_executor_arguments(p)
    p.set_defaults(func=_cmd_autolabel)
