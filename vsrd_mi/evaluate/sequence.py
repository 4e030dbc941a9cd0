"""Evaluation of pseudo labels against KITTI-360 ground truth (protocol: ``docs/evaluation.md``).

:func:`evaluate_frames` works on in-memory boxes (:class:`FrameBoxes`); :func:`evaluate_sequence`
reads KITTI label files of predictions and the ground truth of a KITTI-360 sequence and calls it.

Protocol (all thresholds are :class:`EvalConfig` fields):

* class Car only (other prediction types are skipped);
* the ground truth's 2D box, which sets its difficulty, comes from (``EvalConfig.gt_boxes``)

  - ``"mask"`` (default, the authors' protocol): the frame's instance map. The ground-truth set is
    the cars of the 3D-box file that appear in the frame's instance map, and a car's 2D box is
    the tight box of its visible pixels as ``torchvision.ops.masks_to_boxes`` gives it (first and
    last pixel index, so the height is one less than the number of pixel rows);
  - ``"projected"``: its 3D box projected into the image (:func:`vsrd_mi.geometry.camera.box_to_2d`,
    clipped to the image; height 0 outside it), every car of the 3D-box file present in the
    frame (optionally only those in the instance map: ``gt_visible_in_mask``);

  a prediction's 2D box is the one on its label line;
* difficulty as in the KITTI devkit's ``eval.py``: ground truth counts when its 2D height is
  *greater* than the difficulty's minimum (Easy > 40 px, Hard > 25 px, so Hard includes Easy),
  smaller ground truth is ignored (a prediction matched to it is neither TP nor FP); a prediction
  is ignored when its height is *below* the minimum, and a counted ground-truth car matched by an
  ignored prediction is then neither hit nor miss (it stays in the recall denominator);
* BEV and 3D IoU (exact, :mod:`vsrd_mi.geometry.iou3d`) at 0.3, 0.5 and 0.7, overlap > threshold;
* AP|R40 and AP|R11 on the exact precision curve, and the devkit's 41-threshold curve for
  comparison, with AOS on both (:mod:`vsrd_mi.evaluate.ap` explains them);
* matched-pair statistics and breakdowns (:mod:`vsrd_mi.evaluate.metrics`) over ground truth
  taller than ``pair_min_height`` (by the same 2D boxes), with the per-car attributes of the
  optional sidecar (:mod:`vsrd_mi.evaluate.attributes`).
"""

from __future__ import annotations

import os
import re
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..data.kitti360 import Sequence as KittiSequence
from ..data.kitti_labels import CAR, box_from_label, observation_angle, read_labels
from ..errors import DataError
from ..geometry.boxes import Box3D, kitti_ry_from_yaw
from ..geometry.camera import box_to_2d
from ..geometry.iou3d import iou_matrices
from .ap import CURVE_DESCRIPTIONS, CURVE_EXACT, average_precision
from .attributes import UNKNOWN, CarAttributes, read_attributes
from .matching import FrameMatchInput, orientation_similarity
from .metrics import BreakdownBins, PairStatistics
from .observability import labelling_frames, length_view_shift

#: Names of the two overlap metrics, in result order.
METRIC_BEV, METRIC_3D = "bev", "3d"

#: Prediction file names: the frame index, zero-padded to 10 digits.
PREDICTION_FILE = re.compile(r"^(\d{10})\.txt$")

#: Where the ground truth's 2D boxes (difficulty) and set come from: the instance maps (the
#: authors' protocol) or the projection of the 3D boxes.
GT_BOXES_MASK, GT_BOXES_PROJECTED = "mask", "projected"
GT_BOXES_DESCRIPTIONS = {
    GT_BOXES_MASK: ("ground truth = the cars of the 3D-box file present in the frame's instance map; "
                    "2D box = tight box of the visible pixels (torchvision masks_to_boxes: height = "
                    "last row - first row), as the authors' evaluation"),
    GT_BOXES_PROJECTED: ("ground truth = every car of the 3D-box file in the frame; 2D box = its 3D "
                         "box projected and clipped to the image"),
}


@dataclass
class EvalConfig:
    """Evaluation protocol (``docs/evaluation.md``)."""

    #: Overlap thresholds; a match needs IoU strictly greater than the threshold.
    iou_thresholds: tuple[float, ...] = (0.3, 0.5, 0.7)
    #: Difficulty name -> minimum 2D box height in pixels: ground truth counts when taller than this,
    #: a prediction when at least this tall (the devkit's eval.py).
    min_height: dict[str, float] = field(default_factory=lambda: {"easy": 40.0, "hard": 25.0})
    #: Ground truth taller than this (px) enters the matched-pair statistics (default: Hard).
    pair_min_height: float = 25.0
    #: A Hungarian pair counts as matched when its 3D IoU exceeds this.
    pair_min_iou: float = 0.0
    #: KITTI type of the evaluated class; prediction lines of other types are skipped.
    class_name: str = CAR
    #: Score given to prediction lines without one (15 values); None makes such a line an error.
    default_score: float | None = None
    #: Source of the ground truth's 2D boxes and set: :data:`GT_BOXES_MASK` (the authors'
    #: protocol; needs the instance maps) or :data:`GT_BOXES_PROJECTED`.
    gt_boxes: str = GT_BOXES_MASK
    #: With ``gt_boxes="projected"``: keep only ground-truth cars whose instance appears in the
    #: frame's instance map (KITTI-360 boxes have no occlusion flag: cars hidden behind buildings
    #: would otherwise count as misses). The mask protocol always does.
    gt_visible_in_mask: bool = False
    #: Bins of the distance and occlusion breakdowns.
    bins: BreakdownBins = field(default_factory=BreakdownBins)
    #: Measure for every ground-truth car whether the views that label it see its length
    #: (:mod:`vsrd_mi.evaluate.observability`; the breakdowns ``by_length_view`` and
    #: ``by_class_length_seen``). Reads the instance maps the target selection walks for every
    #: evaluated frame.
    length_views: bool = False

    def __post_init__(self) -> None:
        if self.gt_boxes not in GT_BOXES_DESCRIPTIONS:
            raise ValueError(f"gt_boxes must be one of {sorted(GT_BOXES_DESCRIPTIONS)}, got {self.gt_boxes!r}")


@dataclass(frozen=True)
class FrameBoxes:
    """Ground truth and predictions of one frame, with their 2D box heights (pixels) and, when
    known, the ground truth's attributes (:class:`~vsrd_mi.evaluate.attributes.CarAttributes`)."""

    frame: int
    gt: list[Box3D]
    gt_height: np.ndarray
    pred: list[Box3D]
    pred_score: np.ndarray
    pred_height: np.ndarray
    gt_attributes: Sequence[CarAttributes] | None = None
    #: Names the sequence (its dataset root and name): with the instance ids it tells the cars of
    #: pooled sequences apart, also of sequences of one name under different roots.
    sequence: str = ""

    def __post_init__(self) -> None:
        for name in ("gt_height", "pred_score", "pred_height"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(-1))
        if len(self.gt_height) != len(self.gt):
            raise ValueError(f"frame {self.frame}: {len(self.gt)} ground-truth boxes but "
                             f"{len(self.gt_height)} heights")
        if not len(self.pred) == len(self.pred_score) == len(self.pred_height):
            raise ValueError(f"frame {self.frame}: {len(self.pred)} predictions, "
                             f"{len(self.pred_score)} scores, {len(self.pred_height)} heights")
        attributes = tuple(self.gt_attributes) if self.gt_attributes is not None else (UNKNOWN,) * len(self.gt)
        if len(attributes) != len(self.gt):
            raise ValueError(f"frame {self.frame}: {len(self.gt)} ground-truth boxes but "
                             f"{len(attributes)} attributes")
        object.__setattr__(self, "gt_attributes", attributes)


def projected_heights(boxes: Sequence[Box3D], K: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """2D box heights (px) of ``boxes`` projected with ``K`` and clipped to the image; 0 if outside."""
    heights = []
    for b in boxes:
        box2d = box_to_2d(b, K, image_size=image_size)
        heights.append(0.0 if box2d is None else float(box2d[3] - box2d[1]))
    return np.array(heights, dtype=np.float64)


def mask_box_heights(instance_map: np.ndarray, boxes: Sequence[Box3D]) -> tuple[list[int], np.ndarray]:
    """Indices of ``boxes`` whose instance appears in ``instance_map`` and the heights of their
    2D boxes as ``torchvision.ops.masks_to_boxes`` gives them (last pixel row - first pixel row)."""
    kept, heights = [], []
    for i, b in enumerate(boxes):
        rows = np.flatnonzero((instance_map == b.instance_id).any(axis=1))
        if rows.size:
            kept.append(i)
            heights.append(float(rows[-1] - rows[0]))
    return kept, np.array(heights, dtype=np.float64)


def observation_angles(boxes: Sequence[Box3D]) -> np.ndarray:
    """KITTI observation angle ``alpha`` of each box (radians), from its yaw and centre."""
    return np.array([observation_angle(kitti_ry_from_yaw(b.yaw), b.centre[0], b.centre[2]) for b in boxes])


def _threshold_key(threshold: float) -> str:
    return f"{threshold:g}"


def evaluate_frames(frames: Sequence[FrameBoxes], config: EvalConfig | None = None) -> dict:
    """AP tables and matched-pair statistics of ``frames`` (JSON-ready dict).

    Keys: ``ap[metric][threshold][difficulty]`` with ``R40``, ``R11`` (exact curve), ``devkit_R40``,
    ``devkit_R11``, the same four for AOS (``AOS_R40``, ..., ``devkit_AOS_R11``), ``n_gt``,
    ``max_recall``; ``pairs[group]`` and ``breakdown[name][group]`` (see
    :mod:`vsrd_mi.evaluate.metrics`); ``counts[difficulty]`` with the numbers of counted ground
    truth and predictions; ``protocol`` (configuration and the definitions used).
    """
    config = config or EvalConfig()
    overlaps = [iou_matrices(f.gt, f.pred) for f in frames]
    similarity = [orientation_similarity(observation_angles(f.gt), observation_angles(f.pred)) for f in frames]
    ap: dict[str, dict] = {}
    for m, metric in enumerate((METRIC_BEV, METRIC_3D)):
        ap[metric] = {}
        for threshold in config.iou_thresholds:
            ap[metric][_threshold_key(threshold)] = {
                difficulty: average_precision(
                    [FrameMatchInput(overlap=ov[m], gt_ignored=f.gt_height <= min_h,
                                     det_ignored=f.pred_height < min_h, scores=f.pred_score, similarity=sim)
                     for f, ov, sim in zip(frames, overlaps, similarity)], threshold).to_dict()
                for difficulty, min_h in config.min_height.items()}
    pairs = PairStatistics()
    for f in frames:
        pairs.add_frame(f.gt, f.pred, f.gt_height > config.pair_min_height, config.pair_min_iou,
                        f.gt_attributes, f.frame, f.sequence)
    counts = {d: {"n_gt": int(sum(np.count_nonzero(f.gt_height > h) for f in frames)),
                  "n_pred": int(sum(np.count_nonzero(f.pred_height >= h) for f in frames))}
              for d, h in config.min_height.items()}
    return {"ap": ap, "pairs": pairs.summary(), "breakdown": pairs.breakdowns(config.bins), "counts": counts,
            "n_pred_total": int(sum(len(f.pred) for f in frames)),
            "protocol": {**asdict(config), "headline_curve": CURVE_EXACT,
                         "precision_curves": CURVE_DESCRIPTIONS,
                         "gt_boxes_rule": GT_BOXES_DESCRIPTIONS[config.gt_boxes],
                         "difficulty_rule": "ground truth counts when its 2D height > min_height (px); "
                                            "a prediction is ignored when its 2D height < min_height",
                         "match_rule": "IoU > threshold",
                         "aos_rule": "sum over TPs of (1 + cos(alpha_gt - alpha_pred)) / 2, divided by TP + FP"}}


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


def sequence_frames(pred_dir: str | os.PathLike, gt_root: str | os.PathLike, sequence: int | str,
                    frames: Iterable[int] | None = None, config: EvalConfig | None = None
                    ) -> tuple[list[FrameBoxes], dict]:
    """The :class:`FrameBoxes` of one sequence's evaluated frames (see :func:`evaluate_sequence`
    for which frames and where predictions are read), and a dict of ``sequence``,
    ``prediction_dir``, ``frames``, ``frames_without_predictions``, ``attributes`` and, with
    ``config.length_views``, ``length_views_from_one_frame`` (frames whose selection had too few
    sources, so the frame alone was searched for views of the length). Frames of
    several sequences can be pooled in one :func:`evaluate_frames`."""
    config = config or EvalConfig()
    seq = KittiSequence(gt_root, sequence)
    attributes = read_attributes(seq.root, seq.name)
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
    evaluated, boxes_cache, single_view = [], {}, []
    for f in selected:
        gt, gt_height = ground_truth_and_heights(seq, f, config)
        if f in files:
            pred, score, height = load_predictions(files[f], config)
        else:
            pred, score, height = [], np.empty(0), np.empty(0)
        gt_attributes = [attributes.lookup(f, b.instance_id) for b in gt] if attributes else None
        if config.length_views:
            views = labelling_views(seq, f)
            if views is None:
                single_view.append(f)
            shifts = length_view_shift(seq, views or [f], [b.instance_id for b in gt], cache=boxes_cache)
            gt_attributes = [replace(a, length_view_px=shifts[b.instance_id])
                             for a, b in zip(gt_attributes or [UNKNOWN] * len(gt), gt)]
        evaluated.append(FrameBoxes(frame=f, gt=gt, gt_height=gt_height, pred=pred, pred_score=score,
                                    pred_height=height, gt_attributes=gt_attributes,
                                    sequence=f"{seq.root}/{seq.name}"))
    info = {"sequence": seq.name, "prediction_dir": str(label_dir), "frames": selected,
            "frames_without_predictions": [f for f in selected if f not in files],
            "attributes": str(attributes.path) if attributes else None}
    if config.length_views:
        info["length_views_from_one_frame"] = single_view
    return evaluated, info


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
    config = config or EvalConfig()
    evaluated, info = sequence_frames(pred_dir, gt_root, sequence, frames, config)
    result = evaluate_frames(evaluated, config)
    result.update(info)
    return result


def labelling_views(seq: KittiSequence, frame: int) -> list[int] | None:
    """:func:`~vsrd_mi.evaluate.observability.labelling_frames` of ``frame`` (None: too few
    sources there, the frame alone counts), a DataError saying that the length views need the
    selection's instance maps otherwise."""
    try:
        return labelling_frames(seq, frame)
    except DataError as exc:
        raise DataError(exc.path, f"{exc.problem} (--length-views runs the target selection, which "
                                  f"needs the instance maps)") from None


def ground_truth_and_heights(seq: KittiSequence, frame: int, config: EvalConfig) -> tuple[list[Box3D], np.ndarray]:
    """The ground-truth cars of ``frame`` and their 2D box heights under ``config.gt_boxes``."""
    gt = seq.ground_truth(frame)
    if config.gt_boxes == GT_BOXES_PROJECTED:
        if config.gt_visible_in_mask:
            visible = seq.car_instances(frame).keys()
            gt = [b for b in gt if b.instance_id in visible]
        return gt, projected_heights(gt, seq.calibration.K, seq.calibration.image_size)
    try:
        instance_map = seq.instance_map(frame)
    except DataError as exc:
        raise DataError(exc.path, f"{exc.problem} (the mask protocol, --gt-boxes mask, needs the instance map "
                                  f"of every evaluated frame; --gt-boxes projected does not)") from None
    kept, heights = mask_box_heights(instance_map, gt)
    return [gt[i] for i in kept], heights
