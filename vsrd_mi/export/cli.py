"""``vsrd-mi export-dataset`` (a detector's training set, :mod:`.dataset`) and ``vsrd-mi report``
(a review page of a run, :mod:`.report`)."""

from __future__ import annotations

import argparse
import sys
from typing import Callable

from ..errors import DataError
from .dataset import DUPLICATES_ERROR, DUPLICATES_FIRST, SPLIT_FRAMES, SPLIT_SEQUENCES, ExportConfig, export_dataset
from .report import ReportConfig, write_report


def _unit_interval(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {value}")
    return value


def run_export(args: argparse.Namespace) -> int:
    """Entry point of ``vsrd-mi export-dataset``; returns the exit code (1 on bad input)."""
    try:
        cfg = ExportConfig(min_score=args.min_score, val_fraction=args.val_fraction, split_by=args.split_by,
                           val_sequences=tuple(args.val_sequences or ()), copy_images=args.copy,
                           level=args.level, skip_empty=args.skip_empty, duplicates=args.duplicates,
                           force=args.force)
        summary = export_dataset(args.out, args.runs, args.root, cfg)
    except (DataError, ValueError) as exc:
        print(f"vsrd-mi export-dataset: error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.out}: {summary['n_frames']} frames ({summary['n_train']} train, {summary['n_val']} val) "
          f"from {len(summary['sequences'])} sequence(s), {summary['n_labels']} labels"
          + (" in level cameras" if cfg.level else ""))
    return 0


def run_report(args: argparse.Namespace) -> int:
    """Entry point of ``vsrd-mi report``; returns the exit code (1 on bad input)."""
    try:
        path = write_report(args.run, args.root, ReportConfig(review_below=args.review_below,
                                                               evaluate=not args.no_eval,
                                                               rendered_sources=args.sources))
    except DataError as exc:
        print(f"vsrd-mi report: error: {exc}", file=sys.stderr)
        return 1
    print(path)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export-dataset`` and ``report`` sub-commands."""
    p = subparsers.add_parser(
        "export-dataset", help="write autolabel runs as a KITTI object-detection training set",
        description="Every labelled frame of the runs in the KITTI object-detection layout that detector "
                    "loaders read (mmdetection3d, MonoFlex, MonoDETR): training/image_2/%06d.png, "
                    "training/calib/%06d.txt (P2 = the camera of the labels), training/label_2/%06d.txt "
                    "(score = confidence as the 16th value), ImageSets/{train,val,trainval,test}.txt and "
                    "mapping.txt (line i: '<sequence> <frame>' of index i). See docs/export.md.")
    p.add_argument("out", help="output folder")
    p.add_argument("--from", dest="runs", nargs="+", required=True, metavar="RUN",
                   help="autolabel output folders (RUN/<sequence>/labels/%%010d.txt) or their sequence folders")
    p.add_argument("--root", nargs="+", required=True, metavar="ROOT",
                   help="KITTI-360 root(s) with the runs' images and calibration: one for all runs or one per run")
    p.add_argument("--min-score", type=_unit_interval, default=0.0,
                   help="leave out labels whose score (confidence) is below this (default 0: keep all)")
    p.add_argument("--val-fraction", type=float, default=0.2,
                   help="share of frames (the last frames of each sequence) or of sequences (the last in "
                        "name order) in val.txt (default 0.2; 0: no validation split)")
    p.add_argument("--split-by", choices=(SPLIT_FRAMES, SPLIT_SEQUENCES), default=SPLIT_FRAMES,
                   help="split the frames of every sequence, or whole sequences (default frames)")
    p.add_argument("--val-sequences", nargs="+", metavar="SEQ",
                   help="these sequences (folder names) form the validation split (overrides --val-fraction)")
    p.add_argument("--copy", action="store_true", help="copy the images (default: relative symlinks)")
    p.add_argument("--level", action="store_true",
                   help="exact labels for a pitched / rolled camera: every image warped by the homography "
                        "K R K^-1 of a virtual camera with the same centre and intrinsics whose axes are level "
                        "with the road (level = the world's vertical, z in KITTI-360's cam0_to_world poses); "
                        "same image size, the band the original does not cover filled black; labels, P0-P3 "
                        "and 2D boxes (the level 3D box projected with P2, clipped to the image) in that frame")
    p.add_argument("--skip-empty", action="store_true", help="leave out frames left without labels")
    p.add_argument("--duplicates", choices=(DUPLICATES_ERROR, DUPLICATES_FIRST), default=DUPLICATES_ERROR,
                   help="a frame labelled by several runs: an error (default) or the first run's labels")
    p.add_argument("--force", action="store_true",
                   help="replace an earlier export in OUT (removes training/, ImageSets/, mapping.txt, export.json)")
    func: Callable[[argparse.Namespace], int] = run_export
    p.set_defaults(func=func)

    r = subparsers.add_parser(
        "report", help="write a review page (RUN/report/index.html) of an autolabel run",
        description="A self-contained HTML page (relative links; opens from disk) of an autolabel run: summary "
                    "(targets done / failed, time, settings), the evaluation where the dataset has ground truth, "
                    "and per target its boxes (size, yaw, velocity, confidence; low-confidence boxes flagged for "
                    "review) with the --vis visuals, or visuals rendered from the result files and the dataset.")
    r.add_argument("run", help="autolabel output folder (RUN/<sequence>/...) or one sequence folder")
    r.add_argument("--root", help="KITTI-360 root of the run (evaluation, and visuals of targets without vis/)")
    r.add_argument("--review-below", type=_unit_interval, default=ReportConfig.review_below,
                   help="flag boxes whose confidence is below this for review (default %(default)s)")
    r.add_argument("--sources", type=int, default=ReportConfig.rendered_sources,
                   help="source frames drawn per target when rendering visuals here (default %(default)s)")
    r.add_argument("--no-eval", action="store_true", help="leave the evaluation out")
    report_func: Callable[[argparse.Namespace], int] = run_report
    r.set_defaults(func=report_func)
