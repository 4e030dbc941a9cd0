"""Evaluation of pseudo labels against KITTI-360 ground truth (REFERENCE §9).

:func:`evaluate_frames` works on in-memory boxes (:class:`FrameBoxes`); :func:`evaluate_sequence`
reads KITTI label files of predictions and the ground truth of a KITTI-360 sequence and calls it.

Protocol (all thresholds are :class:`EvalConfig` fields):

* class Car only (other prediction types are skipped);
* difficulty by the 2D box height: the ground truth's from projecting its 3D box into the image
  (:func:`vsrd_mi.geometry.camera.box_to_2d`, clipped to the image; a box outside the image has
  height 0), a prediction's from the 2D box on its label line. A box belongs to a difficulty when
  its height is *strictly greater* than the difficulty's minimum (Easy > 40 px, Hard > 25 px, so
  Hard includes Easy). Smaller ground truth is ignored (a prediction matched to it is neither TP
  nor FP); smaller predictions are ignored unless matched, as in the devkit;
* BEV and 3D IoU (exact, :mod:`vsrd_mi.geometry.iou3d`) at 0.3, 0.5 and 0.7, overlap > threshold;
* AP|R40 and AP|R11 on the exact precision curve, and the devkit's 41-threshold curve for
  comparison (:mod:`vsrd_mi.evaluate.ap` explains both);
* matched-pair statistics (:mod:`vsrd_mi.evaluate.metrics`) over ground truth taller than
  ``pair_min_height``.
"""

from __future__ import annotations

import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..errors import DataError
from ..export.kitti_labels import CAR, box_from_label, read_labels
from ..geometry.boxes import Box3D
from ..geometry.camera import box_to_2d
from ..geometry.iou3d import iou_matrices
from .ap import CURVE_DESCRIPTIONS, CURVE_EXACT, average_precision
from .matching import FrameMatchInput
from .metrics import PairStatistics

#: Names of the two overlap metrics, in result order.
METRIC_BEV, METRIC_3D = "bev", "3d"

#: Prediction file names: the frame index, zero-padded to 10 digits.
PREDICTION_FILE = re.compile(r"^(\d{10})\.txt$")


@dataclass
class EvalConfig:
    """Evaluation protocol; defaults follow REFERENCE §9."""

    #: Overlap thresholds; a match needs IoU strictly greater than the threshold.
    iou_thresholds: tuple[float, ...] = (0.3, 0.5, 0.7)
    #: Difficulty name -> minimum 2D box height in pixels (a box counts when taller than this).
    min_height: dict[str, float] = field(default_factory=lambda: {"easy": 40.0, "hard": 25.0})
    #: Ground truth taller than this (px) enters the matched-pair statistics (default: Hard).
    pair_min_height: float = 25.0
    #: A Hungarian pair counts as matched when its 3D IoU exceeds this.
    pair_min_iou: float = 0.0
    #: KITTI type of the evaluated class; prediction lines of other types are skipped.
    class_name: str = CAR
    #: Score given to prediction lines without one (15 values); None makes such a line an error.
    default_score: float | None = None
    #: Keep only ground-truth cars whose instance appears in the frame's instance map (KITTI-360
    #: boxes have no occlusion flag: cars hidden behind buildings would otherwise count as misses).
    #: Needs the instance maps of the evaluated frames.
    gt_visible_in_mask: bool = False


@dataclass(frozen=True)
class FrameBoxes:
    """Ground truth and predictions of one frame, with their 2D box heights (pixels)."""

    frame: int
    gt: list[Box3D]
    gt_height: np.ndarray
    pred: list[Box3D]
    pred_score: np.ndarray
    pred_height: np.ndarray

    def __post_init__(self) -> None:
        for name in ("gt_height", "pred_score", "pred_height"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(-1))
        if len(self.gt_height) != len(self.gt):
            raise ValueError(f"frame {self.frame}: {len(self.gt)} ground-truth boxes but "
                             f"{len(self.gt_height)} heights")
        if not len(self.pred) == len(self.pred_score) == len(self.pred_height):
            raise ValueError(f"frame {self.frame}: {len(self.pred)} predictions, "
                             f"{len(self.pred_score)} scores, {len(self.pred_height)} heights")


def projected_heights(boxes: Sequence[Box3D], K: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """2D box heights (px) of ``boxes`` projected with ``K`` and clipped to the image; 0 if outside."""
    heights = []
    for b in boxes:
        box2d = box_to_2d(b, K, image_size=image_size)
        heights.append(0.0 if box2d is None else float(box2d[3] - box2d[1]))
    return np.array(heights, dtype=np.float64)


def _threshold_key(threshold: float) -> str:
    return f"{threshold:g}"


def evaluate_frames(frames: Sequence[FrameBoxes], config: EvalConfig | None = None) -> dict:
    """AP tables and matched-pair statistics of ``frames`` (JSON-ready dict).

    Keys: ``ap[metric][threshold][difficulty]`` with ``R40``, ``R11`` (exact curve), ``devkit_R40``,
    ``devkit_R11``, ``n_gt``, ``max_recall``; ``pairs[group]`` (see
    :meth:`vsrd_mi.evaluate.metrics.PairStatistics.summary`); ``counts[difficulty]`` with the
    numbers of counted ground truth and predictions; ``protocol`` (configuration and the precision
    curves' definitions).
    """
    config = config or EvalConfig()
    overlaps = [iou_matrices(f.gt, f.pred) for f in frames]
    ap: dict[str, dict] = {}
    for m, metric in enumerate((METRIC_BEV, METRIC_3D)):
        ap[metric] = {}
        for threshold in config.iou_thresholds:
            ap[metric][_threshold_key(threshold)] = {
                difficulty: average_precision(
                    [FrameMatchInput(overlap=ov[m], gt_ignored=f.gt_height <= min_h,
                                     det_ignored=f.pred_height <= min_h, scores=f.pred_score)
                     for f, ov in zip(frames, overlaps)], threshold).to_dict()
                for difficulty, min_h in config.min_height.items()}
    pairs = PairStatistics()
    for f in frames:
        pairs.add_frame(f.gt, f.pred, f.gt_height > config.pair_min_height, config.pair_min_iou)
    counts = {d: {"n_gt": int(sum(np.count_nonzero(f.gt_height > h) for f in frames)),
                  "n_pred": int(sum(np.count_nonzero(f.pred_height > h) for f in frames))}
              for d, h in config.min_height.items()}
    return {"ap": ap, "pairs": pairs.summary(), "counts": counts,
            "n_pred_total": int(sum(len(f.pred) for f in frames)),
            "protocol": {**asdict(config), "headline_curve": CURVE_EXACT,
                         "precision_curves": CURVE_DESCRIPTIONS,
                         "difficulty_rule": "2D box height > min_height (px)",
                         "match_rule": "IoU > threshold"}}


def load_predictions(path: str | os.PathLike, config: EvalConfig | None = None
                     ) -> tuple[list[Box3D], np.ndarray, np.ndarray]:
    """Boxes, scores and 2D heights of the ``config.class_name`` objects in a label file."""
    config = config or EvalConfig()
    boxes, scores, heights = [], [], []
    for k, label in enumerate(read_labels(path), start=1):
        if label.type != config.class_name:
            continue
        score = label.score if label.score is not None else config.default_score
        if score is None:
            raise DataError(path, f"object {k} ({label.type}) has no score (16th value)")
        try:
            boxes.append(box_from_label(label))
        except ValueError as exc:
            raise DataError(path, f"object {k} ({label.type}) is not a valid box: {exc}") from None
        scores.append(score)
        heights.append(label.height_2d)
    return boxes, np.array(scores, dtype=np.float64), np.array(heights, dtype=np.float64)


def prediction_dir(pred_dir: str | os.PathLike, sequence_names: Iterable[str]) -> Path:
    """Where the label files are: ``pred_dir/<seq>/labels`` if that exists, else ``pred_dir``."""
    pred_dir = Path(pred_dir)
    for name in sequence_names:
        nested = pred_dir / name / "labels"
        if nested.is_dir():
            return nested
    if not pred_dir.is_dir():
        raise DataError(pred_dir, "missing prediction directory")
    return pred_dir


def prediction_files(label_dir: Path) -> dict[int, Path]:
    """Frame index -> label file for every ``%010d.txt`` in ``label_dir``."""
    return {int(m.group(1)): p for p in label_dir.iterdir()
            if (m := PREDICTION_FILE.match(p.name)) and p.is_file()}


def evaluate_sequence(pred_dir: str | os.PathLike, gt_root: str | os.PathLike, sequence: int | str,
                      frames: Iterable[int] | None = None, config: EvalConfig | None = None) -> dict:
    """Evaluate the prediction label files of one KITTI-360 sequence against its ground truth.

    Predictions are read from ``pred_dir/%010d.txt`` or, when it exists,
    ``pred_dir/<sequence>/labels/%010d.txt``. With ``frames=None`` every frame that has a
    prediction file is evaluated (frames without a file are *not* counted as misses). With
    ``frames`` given exactly those frames are evaluated: a listed frame without a prediction file
    counts as having no predictions (all its ground truth missed), prediction files of unlisted
    frames are ignored. Every evaluated frame must be a frame of the sequence (pose and image).
    Returns :func:`evaluate_frames`'s dict plus ``sequence``, ``prediction_dir``, ``frames`` and
    ``frames_without_predictions``.
    """
    from ..data.kitti360 import Sequence

    config = config or EvalConfig()
    seq = Sequence(gt_root, sequence)
    label_dir = prediction_dir(pred_dir, dict.fromkeys([seq.name, str(sequence)]))
    files = prediction_files(label_dir)
    known = set(seq.frames)
    if frames is None:
        if not files:
            raise DataError(label_dir, "no prediction files (%010d.txt) found")
        selected = sorted(files)
        for f in selected:
            if f not in known:
                raise DataError(files[f], f"frame {f} is not a frame of {seq.name} under {seq.root}")
    else:
        selected = sorted(set(int(f) for f in frames))
        if not selected:
            raise DataError(label_dir, "empty frame selection")
        unknown = [f for f in selected if f not in known]
        if unknown:
            raise DataError(seq.root, f"frames {unknown[:10]} are not frames of {seq.name}")
    K, image_size = seq.calibration.K, seq.calibration.image_size
    evaluated = []
    for f in selected:
        gt = seq.ground_truth(f)
        if config.gt_visible_in_mask:
            visible = seq.car_instances(f).keys()
            gt = [b for b in gt if b.instance_id in visible]
        if f in files:
            pred, score, height = load_predictions(files[f], config)
        else:
            pred, score, height = [], np.empty(0), np.empty(0)
        evaluated.append(FrameBoxes(frame=f, gt=gt, gt_height=projected_heights(gt, K, image_size),
                                    pred=pred, pred_score=score, pred_height=height))
    result = evaluate_frames(evaluated, config)
    result.update(sequence=seq.name, prediction_dir=str(label_dir), frames=selected,
                  frames_without_predictions=[f for f in selected if f not in files])
    return result
