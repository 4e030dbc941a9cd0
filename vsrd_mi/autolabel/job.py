"""Autolabel one target frame end to end (the batch job of ``vsrd-mi autolabel``).

:func:`process_target` is the batch job (:mod:`vsrd_mi.batch`): load the target's observations,
initialise boxes (stereo initialisation or the documented default), optimise, compute the
confidence (docs/method.md §7) and write, atomically,

* ``labels/%010d.txt``: KITTI labels for the target and every frame of its group (boxes moved
  into each frame by pose and, for dynamic cars, by velocity), score = confidence;
* ``boxes/%010d.json``: the full parameters and a loss-history summary.

After the batch, ``vsrd-mi autolabel`` fuses each parked car's boxes over the targets that see
it and rewrites those labels (:mod:`vsrd_mi.autolabel.consensus`; ``--set consensus.enabled=false``
keeps every target's own boxes).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..batch.atomic import atomic_write_json
from ..batch.tasks import TargetResult, TargetTask
from ..data.kitti360 import Sequence
from ..data.kitti_labels import write_labels
from ..data.observations import Observations, footprint_in_frame, load_observations
from ..data.selection import SelectionConfig, spec_for_frame
from ..geometry.boxes import Box3D
from ..geometry.boxes2d import iou_matrix
from ..init.sequence import initialise_target
from ..optimise.axis import choose_yaws
from ..optimise.config import PRESETS, AutolabelConfig
from ..optimise.heading import decide_headings
from ..optimise.optimiser import BoxOptimiser
from ..scene.initial import default_initial_boxes
from .consensus import labels_in_frame
from .visualise import write_visuals


def confidence(boxes: list[Box3D], obs: Observations) -> np.ndarray:
    """Per-box confidence (docs/method.md §7): mean 2D IoU of projected vs mask boxes over the frames
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
    """``(start boxes, init reference or None, note, surface points or None)`` for the
    optimisation; surface points per box: ``(points, cameras)`` of its stereo cloud, or None."""
    defaults = default_initial_boxes(obs)
    if not cfg.init:
        dyn = cfg.velocity  # without initialisation every instance may move (velocity from 0)
        return ([Box3D(b.centre, b.size, b.yaw, np.zeros(3), dyn, b.instance_id) for b in defaults], None,
                "default boxes", None)
    inits = initialise_target(seq, spec, cfg.stereo_init)
    surface = [(inits[int(i)].fit_points, inits[int(i)].fit_cameras)
               if int(i) in inits and inits[int(i)].fit_points is not None else None for i in obs.instance_ids]
    boxes = [inits[int(i)].to_box() if int(i) in inits else b for i, b in zip(obs.instance_ids, defaults)]
    missing = [int(i) for i in obs.instance_ids if int(i) not in inits]
    note = "stereo initialisation" + (f" (default box for {missing})" if missing else "")
    # parked cars: the length axis the masks support (axis_seen: the cloud or velocity showed it)
    seen = [inits[int(i)].axis_seen if int(i) in inits else False for i in obs.instance_ids]
    axes = choose_yaws(boxes, obs, cfg.axis, anchor=cfg.weights.init, axis_seen=seen)
    # a turned box's footprint is fitted again along its new length (centre and size move)
    boxes = [inits[int(i)].turned(a.yaw, cfg.stereo_init.footprint).to_box()
             if a.switched and int(i) in inits else dataclasses.replace(b, yaw=a.yaw)
             for i, b, a in zip(obs.instance_ids, boxes, axes)]
    switched = [int(b.instance_id) for b, a in zip(boxes, axes) if a.switched]
    note += f"; axis turned for {switched}" if switched else ""
    return boxes, boxes, note, surface


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
    start, init_ref, note, surface = initial_boxes(seq, spec, obs, cfg)
    optimiser = BoxOptimiser(obs, start, cfg, init_boxes=init_ref, surface_points=surface)
    result = optimiser.run()
    index = np.array([int(np.flatnonzero(obs.instance_ids == i)[0]) for i in result.instance_ids])
    headings = decide_headings(result.boxes, index, obs, cfg.heading)
    boxes = [h.box for h in headings]
    conf = confidence(boxes, obs)
    out = task.sequence_dir
    outputs = []
    group = [int(obs.frames[f]) for f in np.flatnonzero(obs.in_group | (np.arange(obs.num_frames) == 0))]
    for f in np.flatnonzero(obs.in_group | (np.arange(obs.num_frames) == 0)):
        labels = labels_in_frame(boxes, conf, obs.cam_to_opt[f], obs.K[f], obs.image_size, float(obs.dt[f]))
        rel = f"labels/{int(obs.frames[f]):010d}.txt"
        (out / "labels").mkdir(parents=True, exist_ok=True)
        write_labels(out / rel, labels)
        outputs.append(rel)
    summary = {
        "sequence": task.sequence, "target": int(task.frame), "group": group,
        "sources": [int(s) for s in spec.sources], "selection_note": spec.note, "initialisation": note,
        "config": cfg.to_dict(), "steps": result.steps, "seconds": result.seconds,
        "stopped_early": result.stopped_early,
        "boxes": [{**h.box.to_dict(), "confidence": float(c), "heading": h.to_dict(),
                   "length_held_from_inside": bool(result.held_ends is not None and result.held_ends[n].any()),
                   "length_unmeasured": bool(result.unmeasured_lengths is not None
                                             and result.unmeasured_lengths[n]),
                   "length_from_prior": bool(result.length_from_prior is not None and result.length_from_prior[n])}
                  for n, (h, c) in enumerate(zip(headings, conf))],
        "loss": {k: {"first": v[0], "last": v[-1], "min": min(v)} for k, v in result.loss_history.items() if v},
    }
    rel = f"boxes/{int(task.frame):010d}.json"
    atomic_write_json(out / rel, summary)
    outputs.append(rel)
    if vis:  # after the labels; a failing visual is a warning in the JSON, never a failed target
        report = write_visuals(out / "vis" / f"{int(task.frame):010d}", seq, optimiser,
                               dataclasses.replace(result, boxes=boxes), conf)
        summary["visuals"] = report.to_dict(relative_to=out)
        atomic_write_json(out / rel, summary)
        outputs.extend(summary["visuals"]["files"])
    return TargetResult(status="done", seconds=result.seconds, outputs=tuple(outputs))
