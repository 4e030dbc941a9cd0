"""Autolabel one target frame end to end, and the ``vsrd-mi autolabel`` command.

:func:`process_target` is the batch job (:mod:`vsrd_mi.batch`): load the target's observations,
initialise boxes (stereo initialisation or the documented default), optimise, compute the
confidence (REFERENCE §7) and write, atomically,

* ``labels/%010d.txt``: KITTI labels for the target and every frame of its group (boxes moved
  into each frame by pose and, for dynamic cars, by velocity), score = confidence;
* ``boxes/%010d.json``: the full parameters and a loss-history summary.

After the batch, ``vsrd-mi autolabel`` fuses each parked car's boxes over the targets that see
it and rewrites those labels (:mod:`vsrd_mi.optimise.consensus`; ``--set consensus.enabled=false``
keeps every target's own boxes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..batch.atomic import atomic_write_json
from ..batch.tasks import TargetResult, TargetTask
from ..data.kitti360 import Sequence, sequence_name
from ..data.observations import Observations, load_observations
from ..data.selection import SelectionConfig, select_targets, spec_for_frame
from ..errors import DataError
from ..export.kitti_labels import write_labels
from ..geometry.boxes import Box3D
from ..geometry.boxes2d import iou_matrix
from ..geometry.camera import box_to_2d
from ..scene.initial import default_initial_boxes
from .config import PRESETS, AutolabelConfig
from .consensus import apply_consensus, labels_in_frame
from .optimiser import BoxOptimiser


def box_in_frame(box: Box3D, obs: Observations, f: int) -> Box3D:
    """Box (optimisation frame, target time) expressed in frame ``f``'s camera at its time.

    The camera may be pitched: the result keeps only the heading's yaw about the camera's y
    axis (what a KITTI label can hold). Project with :func:`footprint_in_frame`, not this box.
    """
    return box.at_offset(float(obs.dt[f])).transformed(np.linalg.inv(obs.cam_to_opt[f]))


def footprint_in_frame(box: Box3D, obs: Observations, f: int) -> np.ndarray | None:
    """2D footprint of the box (optimisation frame, target time) in frame ``f``'s image: the
    exact projection through the full camera pose (a pitched camera included)."""
    return box_to_2d(box, obs.K[f], world_to_cam=np.linalg.inv(obs.cam_to_opt[f]),
                     image_size=obs.image_size, dt=float(obs.dt[f]))


def confidence(boxes: list[Box3D], obs: Observations) -> np.ndarray:
    """Per-box confidence (REFERENCE §7): mean 2D IoU of projected vs mask boxes over the frames
    of the target's group (target included), Hungarian-matched (maximised); in [0, 1]."""
    frames = np.flatnonzero(obs.in_group | (np.arange(obs.num_frames) == 0))
    n = len(boxes)
    total = np.zeros((n, obs.num_instances))
    for f in frames:
        pred = np.zeros((n, 4))  # boxes outside the image keep an empty box (IoU 0)
        for i, b in enumerate(boxes):
            b2 = footprint_in_frame(b, obs, f)
            if b2 is not None:
                pred[i] = b2
        masks = np.nan_to_num(obs.boxes2d[f], nan=-1e4)
        total += iou_matrix(pred, masks)
    mean = total / max(len(frames), 1)
    rows, cols = linear_sum_assignment(-mean)
    conf = np.zeros(n)
    conf[rows] = mean[rows, cols]
    return np.clip(conf, 0.0, 1.0)


def initial_boxes(seq: Sequence, spec, obs: Observations, cfg: AutolabelConfig):
    """``(start boxes, init reference or None, note)`` for the optimisation."""
    defaults = default_initial_boxes(obs)
    if not cfg.init:
        dyn = cfg.velocity  # without initialisation every instance may move (velocity from 0)
        return [Box3D(b.centre, b.size, b.yaw, np.zeros(3), dyn, b.instance_id) for b in defaults], None, "default boxes"
    from ..init.sequence import initialise_target
    inits = initialise_target(seq, spec)
    boxes = [inits[int(i)].to_box() if int(i) in inits else b for i, b in zip(obs.instance_ids, defaults)]
    missing = [int(i) for i in obs.instance_ids if int(i) not in inits]
    note = "stereo initialisation" + (f" (default box for {missing})" if missing else "")
    return boxes, boxes, note


def process_target(task: TargetTask) -> TargetResult:
    """Batch job: autolabel ``task.frame`` of ``task.sequence`` (see module docstring)."""
    config = dict(task.config)
    vis = bool(config.pop("vis", False))  # visual outputs: not an optimisation setting
    cfg = AutolabelConfig.from_dict(config) if config else PRESETS["default"]()
    cfg = cfg.replace(seed=int(task.seed))
    seq = Sequence(task.root, task.sequence)
    spec = spec_for_frame(seq, task.frame, SelectionConfig())
    obs = load_observations(seq, spec)
    if obs.num_instances == 0:
        return TargetResult(status="skipped", seconds=0.0, outputs=(), error="no target instances")
    start, init_ref, note = initial_boxes(seq, spec, obs, cfg)
    optimiser = BoxOptimiser(obs, start, cfg, init_boxes=init_ref)
    result = optimiser.run()
    conf = confidence(result.boxes, obs)
    out = task.sequence_dir
    outputs = []
    group = [int(obs.frames[f]) for f in np.flatnonzero(obs.in_group | (np.arange(obs.num_frames) == 0))]
    for f in np.flatnonzero(obs.in_group | (np.arange(obs.num_frames) == 0)):
        labels = labels_in_frame(result.boxes, conf, obs.cam_to_opt[f], obs.K[f], obs.image_size, float(obs.dt[f]))
        rel = f"labels/{int(obs.frames[f]):010d}.txt"
        (out / "labels").mkdir(parents=True, exist_ok=True)
        write_labels(out / rel, labels)
        outputs.append(rel)
    summary = {
        "sequence": task.sequence, "target": int(task.frame), "group": group,
        "sources": [int(s) for s in spec.sources], "selection_note": spec.note, "initialisation": note,
        "config": cfg.to_dict(), "steps": result.steps, "seconds": result.seconds,
        "stopped_early": result.stopped_early,
        "boxes": [{**b.to_dict(), "confidence": float(c)} for b, c in zip(result.boxes, conf)],
        "loss": {k: {"first": v[0], "last": v[-1], "min": min(v)} for k, v in result.loss_history.items() if v},
    }
    rel = f"boxes/{int(task.frame):010d}.json"
    atomic_write_json(out / rel, summary)
    outputs.append(rel)
    if vis:  # after the labels; a failing visual is a warning in the JSON, never a failed target
        from ..export.visualise import write_visuals
        report = write_visuals(out / "vis" / f"{int(task.frame):010d}", seq, optimiser, result, conf)
        summary["visuals"] = report.to_dict(relative_to=out)
        atomic_write_json(out / rel, summary)
        outputs.extend(summary["visuals"]["files"])
    return TargetResult(status="done", seconds=result.seconds, outputs=tuple(outputs))


def _frame_range(text: str | None) -> list[int] | None:
    if not text:
        return None
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def _cmd_autolabel(args: argparse.Namespace) -> int:
    from ..batch.cli import executor_kwargs
    from ..batch.runner import run_batch

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
        consensus = apply_consensus(Path(args.out) / seq.name, seq, cfg.consensus)
    except (DataError, OSError) as exc:  # the targets' own labels stay as written
        print(f"vsrd-mi autolabel: consensus of parked cars skipped: {exc}", file=sys.stderr)
        return summary.exit_code()
    if consensus["enabled"]:
        print(f"consensus: {len(consensus['fused'])} parked car(s) fused over {len(consensus['targets'])} "
              f"target(s), {len(consensus['labels_rewritten'])} label file(s) rewritten"
              + "".join(f"\n  left out: {s}" for s in consensus["skipped"]))
    return summary.exit_code()


def register(subparsers) -> None:
    from ..batch.cli import add_executor_arguments

    p = subparsers.add_parser("autolabel", help="optimise 3D boxes for the target frames of a sequence")
    p.add_argument("root", help="KITTI-360 root")
    p.add_argument("--sequence", required=True, type=sequence_name)
    p.add_argument("--out", required=True, help="output directory (labels under OUT/SEQ/)")
    p.add_argument("--frames", help="A-B: frames that may be targets (sources come from the whole sequence)")
    p.add_argument("--config", choices=sorted(PRESETS), default="default")
    p.add_argument("--steps", type=int, help="override the number of optimisation steps")
    p.add_argument("--no-residual", action="store_true",
                   help="no residual distance field (the default preset has none; --set residual=true adds it)")
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
