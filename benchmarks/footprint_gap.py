"""Where is a car's mask box inside its box's projection? The projection loss's bias at the ground truth.

For each target frame the ground-truth boxes are put into the optimisation frame and projected
into every supervised view with the optimiser's own projection (its lanes, its
:func:`vsrd_mi.optimise.losses.projected_boxes`), once as the paper's 8 box corners and once as
the car profile (:class:`vsrd_mi.optimise.config.CarProfile`). Per side it reports the gap
``mask box - projected box`` in pixels, signed so that positive means the mask lies inside
(``x1m - x1p``, ``y1m - y1p``, ``x2p - x2m``, ``y2p - y2m``): what the symmetric projection loss
would close by moving a perfect box. Medians over all lanes and by distance band, and the
medians as a fraction of the box's projected height. Truncated views (the projection touching
the image border) are left out: the loss clips both boxes there.

Usage::

    python benchmarks/footprint_gap.py --out benchmarks/footprint_gap.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import TARGETS, dataset_root, write_results
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.data.observations import load_observations
from vsrd_mi.data.selection import SelectionConfig, spec_for_frame
from vsrd_mi.optimise import losses
from vsrd_mi.optimise.config import default_config
from vsrd_mi.optimise.optimiser import BoxOptimiser

SIDES = ("left", "top", "right", "bottom")
#: Distance bands (m) of the per-band medians.
BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 1e9))
#: A projected side within this many pixels of the image border counts as truncated.
BORDER_PX = 1.0


def target_gaps(root: Path, frame: int) -> list[dict]:
    """One row per supervised (view, car) of a target: gaps of the box and of the profile."""
    seq = Sequence(root, 0)
    spec = spec_for_frame(seq, frame, SelectionConfig())
    obs = load_observations(seq, spec)
    gt = {b.instance_id: b for b in seq.ground_truth(frame)}
    boxes = [gt[int(i)].transformed(obs.cam_to_opt[0]) for i in obs.instance_ids]
    cfg = default_config()
    opt = BoxOptimiser(obs, boxes, cfg)
    lanes = opt._projection_lanes()
    dec = opt.integrator.field.decode()
    target = np.stack([np.array(t) for t in lanes.target], 1)
    box = np.array(lanes.box)
    # camera-frame depth of each lane's box centre: (row 2 of R) . c + t_z
    centres = np.array([b.centre for b in boxes])
    rot_z = np.stack([np.array(lanes.rot[2][j]) for j in range(3)], 1)
    depth = np.einsum("lj,lj->l", rot_z, centres[box]) + np.array(lanes.trans[2])
    bounds = np.array(lanes.bounds)
    proj = {}
    for name, profile in (("box", None), ("profile", cfg.car_profile)):
        x1, y1, x2, y2, _ = losses.projected_boxes(dec, lanes, profile)
        proj[name] = np.stack([np.array(v) for v in (x1, y1, x2, y2)], 1)
    rows = []
    for lane in range(lanes.count):
        p = proj["box"][lane]
        if (p[:2] <= bounds[:2] + BORDER_PX).any() or (p[2:] >= bounds[2:] - BORDER_PX).any():
            continue
        row = {"frame": frame, "instance_id": int(obs.instance_ids[box[lane]]),
               "dynamic": bool(boxes[box[lane]].dynamic), "depth_m": float(depth[lane]),
               "height_px": float(p[3] - p[1])}
        m = target[lane]
        for name, q in proj.items():
            q = q[lane]
            row[name] = [float(m[0] - q[0]), float(m[1] - q[1]), float(q[2] - m[2]), float(q[3] - m[3])]
        rows.append(row)
    return rows


def medians(rows: list[dict]) -> dict:
    out = {"n": len(rows)}
    if not rows:
        return out
    h = np.array([r["height_px"] for r in rows])
    for name in ("box", "profile"):
        g = np.array([r[name] for r in rows])
        out[name] = dict(zip(SIDES, np.median(g, 0).round(2).tolist()))
        out[f"{name}_fraction_of_height"] = dict(zip(SIDES, np.median(g / h[:, None], 0).round(3).tolist()))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-dir", type=Path, default=Path("runs/bench-data"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/footprint_gap.json"))
    ap.add_argument("--targets", nargs="+", default=[f"{d}:{f}" for d, f in TARGETS], metavar="DATASET:FRAME")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    for item in args.targets:
        ds, frame = item.split(":")
        rows += [{"dataset": ds, **r} for r in target_gaps(dataset_root(ds, args.data_dir), int(frame))]
    summary = {"all": medians(rows)}
    for lo, hi in BANDS:
        summary[f"{lo:g}-{hi:g} m" if hi < 1e8 else f">{lo:g} m"] = medians(
            [r for r in rows if lo <= r["depth_m"] < hi])
    for ds in sorted({r["dataset"] for r in rows}):
        summary[ds] = medians([r for r in rows if r["dataset"] == ds])
    write_results(args.out, __doc__, time.perf_counter() - t0, summary=summary, rows=rows)
    for k, v in summary.items():
        print(k, v.get("n"), "box", v.get("box"), "profile", v.get("profile"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
