"""How far do the losses themselves move a perfect box? The box-only objective's bias, measured.

A car is not a box: its mask's tight 2D box is smaller than the projection of its 3D box (roof
and bumper corners are rounded off, the roof is set in), and its silhouette is smaller than the
box's. Both image terms of the box-only objective (the projection loss and the box-SDF
silhouette) are therefore minimised by boxes smaller than the car, or turned so that they
project smaller. This script separates that bias from the initialisation's error: for each
target frame it runs the same optimisation twice,

* ``from-init``: from the stereo initialisation (what ``vsrd-mi autolabel`` does);
* ``from-gt``: from the ground-truth boxes, with the ground truth also as the init regulariser's
  and the size / yaw prior's reference (every prior pulls towards the right answer);

and reports the mean 3D IoU of parked and moving cars against the ground truth, with signed
size errors (prediction - ground truth, metres) and yaw errors (degrees). ``from-gt`` is an
upper bound of what the objective allows: what it loses is the loss's bias, not the start's.

Usage::

    python benchmarks/loss_bias.py --out benchmarks/loss_bias.json [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from common import TARGETS, dataset_root, write_results
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.data.observations import load_observations
from vsrd_mi.data.selection import SelectionConfig, spec_for_frame
from vsrd_mi.evaluate.metrics import hungarian_pairs, yaw_error_mod_pi
from vsrd_mi.autolabel.job import initial_boxes
from vsrd_mi.data.observations import box_in_frame
from vsrd_mi.optimise.config import AutolabelConfig, default_config
from vsrd_mi.optimise.optimiser import BoxOptimiser

STARTS = ("from-init", "from-gt")


def run_target(root: Path, frame: int, start: str, cfg: AutolabelConfig) -> list[dict]:
    """Optimise one target frame from ``start``; one row per ground-truth car of the frame."""
    seq = Sequence(root, 0)
    spec = spec_for_frame(seq, frame, SelectionConfig())
    obs = load_observations(seq, spec)
    gt = {b.instance_id: b for b in seq.ground_truth(frame)}
    if start == "from-gt":
        boxes = [gt[int(i)].transformed(obs.cam_to_opt[0]) for i in obs.instance_ids]
        reference = boxes
    else:
        boxes, reference, _ = initial_boxes(seq, spec, obs, cfg)
    result = BoxOptimiser(obs, boxes, cfg, init_boxes=reference).run()
    rows = []
    for box, iid in zip(result.boxes, obs.instance_ids):
        g, p = gt[int(iid)], box_in_frame(box, obs, 0)
        (_, _, iou_bev, iou_3d), = hungarian_pairs([g], [p], min_iou=-1.0)
        rows.append({"instance_id": int(iid), "dynamic": bool(g.dynamic), "iou_3d": iou_3d,
                     "iou_bev": iou_bev, "size_error_m": (p.size - g.size).round(3).tolist(),
                     "yaw_error_deg": float(np.degrees(yaw_error_mod_pi(p.yaw, g.yaw))),
                     "range_error_m": float(np.linalg.norm(p.centre[[0, 2]]) - np.linalg.norm(g.centre[[0, 2]])),
                     "steps": result.steps})
    return rows


def summarise(rows: list[dict]) -> dict:
    out = {}
    for start in STARTS:
        for group, dyn in (("parked", False), ("moving", True)):
            sel = [r for r in rows if r["start"] == start and r["dynamic"] == dyn]
            if sel:
                out[f"{start}/{group}"] = {
                    "n": len(sel), "mean_iou_3d": float(np.mean([r["iou_3d"] for r in sel])),
                    "mean_size_error_m": np.mean([r["size_error_m"] for r in sel], axis=0).round(3).tolist(),
                    "mean_abs_yaw_error_deg": float(np.mean([r["yaw_error_deg"] for r in sel]))}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-dir", type=Path, default=Path("runs/bench-data"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/loss_bias.json"))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="configuration override applied to both starts (as vsrd-mi autolabel --set)")
    ap.add_argument("--targets", nargs="+", default=[f"{d}:{f}" for d, f in TARGETS], metavar="DATASET:FRAME",
                    help="target frames (default: the six of shape_prior.py)")
    ap.add_argument("--starts", nargs="+", default=list(STARTS), choices=STARTS)
    args = ap.parse_args(argv)
    targets = [(t.split(":")[0], int(t.split(":")[1])) for t in args.targets]
    cfg = default_config().with_overrides(args.overrides)
    rows = []
    t0 = time.perf_counter()
    for ds, frame in targets:
        root = dataset_root(ds, args.data_dir)
        for start in args.starts:
            for row in run_target(root, frame, start, cfg):
                rows.append({"dataset": ds, "frame": frame, "start": start, **row})
                print(json.dumps(rows[-1]), flush=True)
    summary = summarise(rows)
    write_results(args.out, __doc__, time.perf_counter() - t0, overrides=args.overrides,
                  weights=dataclasses.asdict(cfg.weights), summary=summary, rows=rows)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
