"""``vsrd-mi eval``: pseudo labels of a KITTI-360 sequence against its ground truth."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable

from ..errors import DataError
from ..geometry.camera import LENGTH_PROBE_M
from .metrics import LENGTH_SEEN_PX
from .sequence import GT_BOXES_DESCRIPTIONS, GT_BOXES_MASK, METRIC_3D, METRIC_BEV, EvalConfig, evaluate_sequence

#: Column layout of the AP table: (difficulty, result key) pairs, per precision curve.
AP_COLUMNS = {
    "exact": [("easy", "R40"), ("hard", "R40"), ("easy", "R11"), ("hard", "R11")],
    "devkit": [("easy", "devkit_R40"), ("hard", "devkit_R40"),
               ("easy", "devkit_R11"), ("hard", "devkit_R11")],
}
METRIC_LABELS = {METRIC_BEV: "AP_BEV", METRIC_3D: "AP_3D"}
#: Row labels of the AOS table, per matching metric.
AOS_LABELS = {METRIC_BEV: "AOS(BEV", METRIC_3D: "AOS(3D"}
#: Breakdown tables printed after the matched pairs (result key, title).
BREAKDOWNS = (("by_class", "vehicle class"), ("by_distance", "distance"),
              ("by_occlusion", "occlusion"), ("by_parking", "parking"),
              ("by_length_view", "whether a view that labels the car sees its length (--length-views)"),
              ("by_class_length_seen", "vehicle class, cars whose length a view sees (--length-views)"))
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


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100.0 * value:.0f}%"


def _bias(summary: dict, extent: str) -> str:
    bias = summary.get("size_bias")
    return "-" if bias is None else f"{100.0 * bias[extent]['mean_rel']:+.1f}%"


def _bias_interval(summary: dict, extent: str) -> str:
    bias = summary.get("size_bias")
    if bias is None:
        return "-"
    b = bias[extent]
    lo, hi = b["mean_rel_ci95"]
    return f"{100.0 * b['mean_rel']:+.1f}% [{100.0 * lo:+.1f}, {100.0 * hi:+.1f}]"


def bias_interval_table(groups: dict) -> list[str]:
    """Rows of the signed size bias with its 95 % interval over cars, per group."""
    lines = [f"{'':12s}{'cars':>6s}{'dL [95 % over cars]':>26s}{'dW':>26s}{'dH':>26s}"]
    for name, s in groups.items():
        cars = s["size_bias"]["n_cars"] if s.get("size_bias") else 0
        lines.append(f"{name:12s}{cars:6d}" + "".join(f"{_bias_interval(s, e):>26s}"
                                                      for e in ("length", "width", "height")))
    return lines


def _ap_tables(result: dict) -> list[str]:
    lines: list[str] = []
    for curve, columns in AP_COLUMNS.items():
        header = f"{'':14s}" + "".join(f"{d.capitalize() + ' ' + k.split('_')[-1]:>10s}" for d, k in columns)
        lines += ["", CURVE_TITLES[curve], header]
        for metric in (METRIC_BEV, METRIC_3D):
            for threshold, by_difficulty in result["ap"][metric].items():
                row = f"{METRIC_LABELS[metric] + '@' + threshold:14s}"
                row += "".join(f"{_fmt(by_difficulty[d][k], '.2f'):>10s}" for d, k in columns)
                lines.append(row)
        lines.append("AOS (orientation similarity of the same matches):")
        for metric in (METRIC_BEV, METRIC_3D):
            for threshold, by_difficulty in result["ap"][metric].items():
                row = f"{AOS_LABELS[metric] + '@' + threshold + ')':14s}"
                row += "".join(f"{_fmt(by_difficulty[d][k.replace('R', 'AOS_R', 1)], '.2f'):>10s}"
                               for d, k in columns)
                lines.append(row)
    return lines


def _summary_header(first: str) -> str:
    return (f"{first:12s}{'n_gt':>6s}{'cars':>6s}{'match':>7s}{'miss':>6s}{'IoU_BEV':>9s}{'IoU_3D':>8s}{'rw3D':>7s}"
            f"{'centre_m':>10s}{'yaw180':>8s}{'head':>6s}{'dL':>8s}{'dW':>8s}{'dH':>8s}")


def _summary_row(name: str, s: dict) -> str:
    return (f"{name:12s}{s['n_gt']:6d}{s['n_cars']:6d}{s['n_matched']:7d}{_pct(s['missed_share']):>6s}"
            f"{_fmt(s['mean_iou_bev'], '.3f'):>9s}{_fmt(s['mean_iou_3d'], '.3f'):>8s}"
            f"{_fmt(s['recall_weighted_iou_3d'], '.3f'):>7s}{_fmt(s['centre_error_m'], '.3f'):>10s}"
            f"{_fmt(s['yaw_error_deg'], '.2f'):>8s}{_pct(s['heading_accuracy']):>6s}"
            f"{_bias(s, 'length'):>8s}{_bias(s, 'width'):>8s}{_bias(s, 'height'):>8s}")


def format_table(result: dict) -> str:
    """Human-readable AP / AOS, matched-pair and breakdown tables of an :func:`evaluate_sequence`
    result."""
    counts, protocol = result["counts"], result["protocol"]
    lines = [f"Sequence {result['sequence']}: {len(result['frames'])} frames "
             f"({len(result['frames_without_predictions'])} without predictions), "
             f"{result['n_pred_total']} Car predictions; counted GT "
             + ", ".join(f"{d} {c['n_gt']}" for d, c in counts.items()),
             f"Ground-truth 2D boxes: {protocol['gt_boxes']} ({protocol['gt_boxes_rule']})"]
    lines += _ap_tables(result)
    lines += ["", f"Matched pairs (Hungarian on 3D IoU > {protocol['pair_min_iou']:g}, "
                  f"GT 2D height > {protocol['pair_min_height']:g} px): n_gt = GT boxes over the frames, cars = "
                  f"distinct cars among them, miss = GT without a box, rw3D = "
                  f"unmatched GT count as 0, yaw180 = mean yaw error modulo 180 deg, head = heading "
                  f"right (error < 90 deg), dL/dW/dH = mean signed size error relative to the truth",
              _summary_header("")]
    lines += [_summary_row(group, s) for group, s in result["pairs"].items()]
    for key, title in BREAKDOWNS:
        groups = result["breakdown"].get(key)
        if groups is None:
            if key in ("by_class", "by_occlusion", "by_parking"):
                lines += ["", f"By {title}: not available (no attributes sidecar with it)"]
            continue
        lines += ["", f"By {title}:", _summary_header("")]
        lines += [_summary_row(name, s) for name, s in groups.items()]
        if key == "by_class":
            lines += ["", "Size bias by vehicle class, with a 95 % interval from resampling the matched cars "
                          "(a class's records are few cars, each counted once per frame; with under ~10 cars "
                          "the interval is too narrow):"]
            lines += bias_interval_table(groups)
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``vsrd-mi eval``; returns the exit code (1 on bad input)."""
    config = EvalConfig(gt_boxes=args.gt_boxes, gt_visible_in_mask=args.visible_only,
                        length_views=args.length_views)
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
        description="AP_BEV / AP_3D and AOS (R40 and R11, exact and devkit precision curves) at "
                    "IoU 0.3, 0.5 and 0.7 for Easy (2D height > 40 px) and Hard (> 25 px) cars; mean "
                    "IoUs, errors, heading accuracy, size bias and the share of cars without a box "
                    "of Hungarian-matched pairs, split static / dynamic and by vehicle class, "
                    "distance, occlusion and parking (the last three need the attributes sidecar "
                    "<root>/data_3d_bboxes/train/<seq>.attributes.json). See docs/evaluation.md.")
    p.add_argument("--pred", required=True,
                   help="prediction directory: DIR/%%010d.txt or DIR/<sequence>/labels/%%010d.txt")
    p.add_argument("--gt", required=True, help="KITTI-360 root (calibration, data_poses, data_2d_raw, "
                                               "data_3d_bboxes)")
    p.add_argument("--sequence", required=True, help="sequence name or number (e.g. 0 or "
                                                     "2013_05_28_drive_0000_sync)")
    p.add_argument("--frames", type=parse_frames, default=None,
                   help="frames to evaluate, e.g. 100-200 or 5,7-9; listed frames without a "
                        "prediction file count as all missed (default: every frame with a file)")
    p.add_argument("--gt-boxes", choices=sorted(GT_BOXES_DESCRIPTIONS), default=GT_BOXES_MASK,
                   help="where the ground truth's 2D boxes (difficulty) and set come from: 'mask' "
                        "(default, the authors' protocol): cars in the frame's instance map, tight box of "
                        "the visible pixels; 'projected': every car of the 3D-box file, its 3D box "
                        "projected into the image. The output names the one used")
    p.add_argument("--visible-only", action="store_true",
                   help="with --gt-boxes projected: keep only GT cars present in the frame's instance map")
    p.add_argument("--length-views", action="store_true",
                   help=f"split the pairs by whether some view that labels the car sees its length: one "
                        f"whose 2D box moves by {LENGTH_SEEN_PX:g} px when the car's far end moves out "
                        f"{LENGTH_PROBE_M:g} m (a car straight ahead in the lane shows only its rear); runs "
                        f"the target selection for every frame, which reads instance maps")
    p.add_argument("--json", action="store_true", help="print the full result as JSON")
    func: Callable[[argparse.Namespace], int] = run
    p.set_defaults(func=func)
