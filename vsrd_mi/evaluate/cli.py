"""``vsrd-mi eval``: pseudo labels of a KITTI-360 sequence against its ground truth."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable

from ..errors import DataError
from .sequence import METRIC_3D, METRIC_BEV, EvalConfig, evaluate_sequence

#: Column layout of the AP table: (difficulty, result key) pairs, per precision curve.
AP_COLUMNS = {
    "exact": [("easy", "R40"), ("hard", "R40"), ("easy", "R11"), ("hard", "R11")],
    "devkit": [("easy", "devkit_R40"), ("hard", "devkit_R40"),
               ("easy", "devkit_R11"), ("hard", "devkit_R11")],
}
METRIC_LABELS = {METRIC_BEV: "AP_BEV", METRIC_3D: "AP_3D"}
#: Table titles of the two precision curves (their definitions are in the JSON ``protocol``).
CURVE_TITLES = {
    "exact": "AP, exact precision curve (every score threshold)",
    "devkit": "AP, KITTI devkit curve (<= 41 kept thresholds; reads up to ~2 AP high on large "
              "sets, too low with fewer than 41 ground-truth boxes)",
}


def parse_frames(text: str) -> list[int]:
    """Frame selection ``A-B`` (inclusive), ``A``, or a comma-separated list of those."""
    frames: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        try:
            a = int(lo)
            b = int(hi) if sep else a
        except ValueError:
            raise argparse.ArgumentTypeError(f"bad frame range {part!r} (expected A-B or A)") from None
        if a < 0 or b < a:
            raise argparse.ArgumentTypeError(f"bad frame range {part!r} (need 0 <= A <= B)")
        frames.extend(range(a, b + 1))
    return frames


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def format_table(result: dict) -> str:
    """Human-readable AP and matched-pair tables of an :func:`evaluate_sequence` result."""
    counts = result["counts"]
    lines = [f"Sequence {result['sequence']}: {len(result['frames'])} frames "
             f"({len(result['frames_without_predictions'])} without predictions), "
             f"{result['n_pred_total']} Car predictions; counted GT "
             + ", ".join(f"{d} {c['n_gt']}" for d, c in counts.items())]
    for curve, columns in AP_COLUMNS.items():
        lines += ["", CURVE_TITLES[curve],
                  f"{'':14s}" + "".join(f"{d.capitalize() + ' ' + k.split('_')[-1]:>10s}"
                                        for d, k in columns)]
        for metric in (METRIC_BEV, METRIC_3D):
            for threshold, by_difficulty in result["ap"][metric].items():
                row = f"{METRIC_LABELS[metric] + '@' + threshold:14s}"
                row += "".join(f"{_fmt(by_difficulty[d][k], '.2f'):>10s}" for d, k in columns)
                lines.append(row)
    protocol = result["protocol"]
    lines += ["", f"Matched pairs (Hungarian on 3D IoU > {protocol['pair_min_iou']:g}, "
                  f"GT 2D height > {protocol['pair_min_height']:g} px; rw = unmatched GT count as 0; "
                  f"yaw error modulo 180 deg)",
              f"{'':9s}{'n_gt':>6s}{'match':>7s}{'IoU_BEV':>9s}{'IoU_3D':>8s}{'rwBEV':>7s}{'rw3D':>7s}"
              f"{'centre_m':>10s}{'yaw_deg':>9s}"]
    for group, s in result["pairs"].items():
        lines.append(f"{group:9s}{s['n_gt']:6d}{s['n_matched']:7d}{_fmt(s['mean_iou_bev'], '.3f'):>9s}"
                     f"{_fmt(s['mean_iou_3d'], '.3f'):>8s}{_fmt(s['recall_weighted_iou_bev'], '.3f'):>7s}"
                     f"{_fmt(s['recall_weighted_iou_3d'], '.3f'):>7s}{_fmt(s['centre_error_m'], '.3f'):>10s}"
                     f"{_fmt(s['yaw_error_deg'], '.2f'):>9s}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``vsrd-mi eval``; returns the exit code (1 on bad input)."""
    config = EvalConfig(gt_visible_in_mask=args.visible_only)
    try:
        result = evaluate_sequence(args.pred, args.gt, args.sequence, frames=args.frames, config=config)
    except DataError as exc:
        print(f"vsrd-mi eval: error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(result, indent=2) if args.json else format_table(result))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``eval`` sub-command."""
    p = subparsers.add_parser(
        "eval", help="evaluate KITTI-format pseudo labels against KITTI-360 ground truth",
        description="AP_BEV / AP_3D (R40 and R11, exact and devkit precision curves) at IoU 0.3, "
                    "0.5 and 0.7 for Easy (2D height > 40 px) and Hard (> 25 px) cars, and mean "
                    "IoUs / errors of Hungarian-matched pairs split static / dynamic.")
    p.add_argument("--pred", required=True,
                   help="prediction directory: DIR/%%010d.txt or DIR/<sequence>/labels/%%010d.txt")
    p.add_argument("--gt", required=True, help="KITTI-360 root (calibration, data_poses, data_2d_raw, "
                                               "data_3d_bboxes)")
    p.add_argument("--sequence", required=True, help="sequence name or number (e.g. 0 or "
                                                     "2013_05_28_drive_0000_sync)")
    p.add_argument("--frames", type=parse_frames, default=None,
                   help="frames to evaluate, e.g. 100-200 or 5,7-9; listed frames without a "
                        "prediction file count as all missed (default: every frame with a file)")
    p.add_argument("--visible-only", action="store_true",
                   help="keep only GT cars present in the frame's instance map")
    p.add_argument("--json", action="store_true", help="print the full result as JSON")
    func: Callable[[argparse.Namespace], int] = run
    p.set_defaults(func=func)
