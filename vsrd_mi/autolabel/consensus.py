"""Sequence-level consensus of parked cars (not in the paper).

Each target frame is optimised on its own, so a parked car seen by several targets gets one box
per target, and those boxes differ by each target's own error: the same car 30 m ahead came out
1 degree off in yaw in one target and 16 in the next (synthetic seed 4404). A parked car is one
rigid object for the whole sequence, so after every target is done the boxes of each parked
instance (KITTI-360's instance ids are global per sequence) are brought into one gravity-aligned
frame and fused:

* contributors: the boxes of instance ``i`` labelled parked, one per target, expressed in the
  optimisation frame of the run's first target (``T_ref @ inv(T_t)``; every optimisation frame
  is gravity-aligned, so this is a rotation about the vertical and a translation);
* weights: a contributor counts ``1 / max(r, ConsensusConfig.near_range)^2``, ``r`` the car's range
  from its target's camera: stereo depth errors and the image evidence of a car both scale with
  its range squared, so the target that saw a car from 15 m knows it about 9 times better than one
  that saw it from 45 m;
* inliers: contributors whose centre lies within ``gate`` metres of the contributors' weighted
  median centre (a car that was parked in two places, or one target's wrong box, is not averaged
  in); they all get the fused box;
* the axis: the inliers whose axis lies within ``axis_gate`` degrees of the axis that carries the
  most weight times confidence (:func:`axis_inliers`) are the ones fused: a box standing across
  the car is a wrong box, and averaging it in gives a diagonal that no target found. Of two
  targets that disagree, the one whose box matches the car's masks better wins: where the axes
  cross, every box's confidence is measured again over the frames of all the targets that see
  the car, so that each is scored on the same views (a target that saw a car only end-on may
  turn its box across the car and still match its own frames' masks as well as the right box
  does, but not the masks of a target that passed the car);
* the fused box: component-wise weighted median of the fused boxes' centres and sizes, and their
  weighted mean axis ``yaw = arg(sum_k w_k exp(2 i yaw_k)) / 2`` (period pi: a box turned end for
  end is the same box);
  its front is where the fused boxes' heading evidence (:mod:`vsrd_mi.optimise.heading`: each
  target's deciding cue, lamps, red balance, silhouettes or bare ends, for its box's own front;
  summed over the targets) points when that sum exceeds the evidence
  threshold, else where most inliers face (a tie: the first inlier).

The fused box replaces every inlier's box in the labels of that inlier's group; its score is the
confidence of docs/method.md §7 for the instance, recomputed over all those groups' frames (mean 2D
IoU of the projected box and the instance's mask box, 0 where the instance has no mask). Moving
cars, and parked cars seen by fewer than ``min_targets`` targets, keep their target's box. The
per-target results (``boxes/%010d.json``) are never changed, so the step can be rerun at any
time; ``consensus.json`` records what was fused.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from ..batch.atomic import atomic_write_json
from ..batch.manifest import MANIFEST_NAME, Manifest
from ..data.kitti360 import Sequence
from ..data.kitti_labels import KittiLabel, label_from_box, write_labels
from ..data.masks import car_values, tight_box
from ..data.observations import opt_from_world
from ..errors import DataError
from ..geometry.boxes import Box3D, axis_difference
from ..geometry.boxes2d import iou_matrix
from ..geometry.camera import box_to_2d
from ..optimise.config import ConsensusConfig, HeadingConfig


@dataclass(frozen=True)
class TargetBoxes:
    """One target's optimised boxes as written to ``boxes/%010d.json``."""

    target: int
    #: Frames labelled from this target (the target and its group).
    group: tuple[int, ...]
    #: Boxes in the target's optimisation frame (:func:`vsrd_mi.data.observations.opt_from_world`).
    boxes: tuple[Box3D, ...]
    confidences: tuple[float, ...]
    #: Per box, its heading decision's evidence for the box's own front over its back (0 when none).
    heading_evidence: tuple[float, ...] = ()

    @staticmethod
    def read(path: Path) -> "TargetBoxes":
        """Parse ``path``; a damaged file raises :class:`DataError` naming it."""
        try:
            d = json.loads(Path(path).read_text())
            boxes = tuple(Box3D.from_dict(b) for b in d["boxes"])
            return TargetBoxes(int(d["target"]), tuple(int(f) for f in d["group"]), boxes,
                               tuple(float(b["confidence"]) for b in d["boxes"]),
                               tuple(float(b.get("heading", {}).get("evidence", 0.0)) for b in d["boxes"]))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DataError(path, f"unreadable target result: {exc}") from exc


@dataclass(frozen=True)
class FusedCar:
    """A parked car's consensus box (in the reference target's optimisation frame)."""

    instance_id: int
    box: Box3D
    #: Targets whose box was fused (inliers) and those left out by the gate.
    targets: tuple[int, ...]
    outliers: tuple[int, ...]
    #: Largest distance (m) of an inlier's centre from the fused centre.
    spread: float
    confidence: float = float("nan")

    def to_dict(self) -> dict:
        return {"instance_id": self.instance_id, "box": self.box.to_dict(), "targets": list(self.targets),
                "outliers": list(self.outliers), "spread_m": self.spread, "confidence": self.confidence}


def weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Component-wise weighted median of ``values`` (N, D): the value where the cumulative weight
    reaches half, or the mean of the two values around it where a value's cumulative weight is
    exactly half (so equal weights give ``np.median``)."""
    values = np.asarray(values, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    out = np.empty(values.shape[1:])
    for j in np.ndindex(out.shape):
        col = values[(slice(None),) + j]
        order = np.argsort(col, kind="stable")
        cum = np.cumsum(w[order])
        half = 0.5 * cum[-1]
        i = int(np.searchsorted(cum, half))
        tie = np.isclose(cum[i], half, rtol=1e-12, atol=0.0) and i + 1 < len(col)
        out[j] = 0.5 * (col[order][i] + col[order][i + 1]) if tie else col[order][i]
    return out


def axis_mean(yaws: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Weighted mean orientation of period pi, ``arg(sum w exp(2 i yaw)) / 2``, turned to point
    within 90 degrees of ``yaws[0]``'s heading (equal weights when None)."""
    yaws = np.asarray(yaws, dtype=np.float64)
    w = np.ones(len(yaws)) if weights is None else np.asarray(weights, dtype=np.float64)
    mean = 0.5 * math.atan2((w * np.sin(2 * yaws)).sum(), (w * np.cos(2 * yaws)).sum())
    if math.cos(mean - yaws[0]) < 0:
        mean += math.pi
    return math.atan2(math.sin(mean), math.cos(mean))


def axis_inliers(yaws: np.ndarray, weights: np.ndarray, gate_rad: float) -> np.ndarray:
    """Mask of the axes within ``gate_rad`` of the modal axis: the one whose neighbours within the
    gate carry the most weight (ties: the heavier, then the first). Of two boxes that disagree
    only the heavier is left."""
    yaws = np.asarray(yaws, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    close = axis_difference(yaws[:, None], yaws[None, :]) <= gate_rad
    support = close @ w
    best = max(range(len(yaws)), key=lambda k: (support[k], w[k], -k))
    return close[best]


def fused_front(axis: float, yaws: np.ndarray, evidence: np.ndarray, min_evidence: float) -> float:
    """``axis`` or ``axis + pi``: where the boxes' summed heading evidence points (each box's
    evidence is for its own yaw) when its magnitude exceeds ``min_evidence``, else where most
    boxes face (``axis`` on a tie)."""
    along = np.where(np.cos(np.asarray(yaws) - axis) >= 0, 1.0, -1.0)
    total = float(np.sum(along * np.asarray(evidence, dtype=np.float64)))
    votes = total if abs(total) > min_evidence else float(np.sum(along))
    return axis if votes >= 0 else math.atan2(math.sin(axis + math.pi), math.cos(axis + math.pi))


def fuse_boxes(boxes: list[Box3D], gate: float, evidence: np.ndarray | None = None,
               min_evidence: float = 0.0, weights: np.ndarray | None = None,
               axis_gate_deg: float = 90.0, confidences: np.ndarray | None = None,
               axis_by_confidence: bool = False) -> tuple[Box3D, np.ndarray] | None:
    """Consensus of one parked car's boxes (one frame): see the module docstring. ``evidence``:
    each box's heading evidence for its own yaw (None: none); ``weights``: each box's weight
    (None: equal); ``axis_gate_deg``: the axis gate (90: none); ``confidences``: each box's
    confidence, which scales its say in the axis (None: equal); ``axis_by_confidence``: the
    confidences alone, not times the weights, are the boxes' say in the axis (confidences
    measured over the same frames for every box).

    Returns the fused box and the inlier mask (the boxes it replaces), or None when fewer than
    two boxes are inliers.
    """
    centres = np.array([b.centre for b in boxes])
    w = np.ones(len(boxes)) if weights is None else np.asarray(weights, dtype=np.float64)
    inliers = np.linalg.norm(centres - weighted_median(centres, w), axis=1) <= gate
    if inliers.sum() < 2:
        return None
    say = w if confidences is None else np.asarray(confidences, dtype=np.float64) * (1.0 if axis_by_confidence else w)
    all_yaws = np.array([b.yaw for b in boxes])
    fused_mask = inliers.copy()
    fused_mask[inliers] = axis_inliers(all_yaws[inliers], say[inliers], math.radians(axis_gate_deg))
    kept = [b for b, k in zip(boxes, fused_mask) if k]
    wk, yaws = w[fused_mask], all_yaws[fused_mask]
    kept_evidence = np.zeros(len(kept)) if evidence is None else np.asarray(evidence, dtype=np.float64)[fused_mask]
    yaw = fused_front(axis_mean(yaws, wk), yaws, kept_evidence, min_evidence)
    fused = Box3D(centre=weighted_median(np.array([b.centre for b in kept]), wk),
                  size=weighted_median(np.array([b.size for b in kept]), wk), yaw=yaw,
                  instance_id=kept[0].instance_id)
    return fused, inliers


class Contribution(NamedTuple):
    """One target's box of a parked car, in the reference frame, and what it brings to the fusion."""

    target: int
    box: Box3D
    #: Heading evidence for the box's own front (0 when none).
    evidence: float
    #: ``1 / max(range, near_range)^2``, the range from the target's camera.
    weight: float
    #: The box's confidence (docs/method.md §7; 0 when unknown).
    confidence: float


def crossed(yaws: np.ndarray, gate_deg: float) -> bool:
    """Whether two of the axes ``yaws`` (radians) differ by more than ``gate_deg`` degrees."""
    yaws = np.asarray(yaws, dtype=np.float64)
    return bool(np.any(axis_difference(yaws[:, None], yaws[None, :]) > math.radians(gate_deg)))


def fuse_parked_cars(results: list[TargetBoxes], to_reference: dict[int, np.ndarray],
                     cfg: ConsensusConfig, min_evidence: float = HeadingConfig.min_evidence,
                     rescore: Callable[[list[Box3D], list[int]], np.ndarray] | None = None) -> list[FusedCar]:
    """Fuse every parked instance seen by at least ``cfg.min_targets`` targets.

    ``to_reference[t]`` maps target ``t``'s optimisation frame to the reference frame (4x4);
    ``min_evidence`` is the heading evidence that decides a fused car's front
    (:class:`~vsrd_mi.optimise.config.HeadingConfig`). ``rescore(boxes, targets)``: the
    confidences of one car's boxes (reference frame) over the frames of all those targets, used
    in place of each target's own where the boxes' axes cross (None: the targets' own).
    """
    seen: dict[int, list[Contribution]] = {}
    for r in results:
        evidence = r.heading_evidence or (0.0,) * len(r.boxes)
        for b, e, c in zip(r.boxes, evidence, r.confidences):
            if not b.dynamic:  # the box's range from its own target's camera sets its weight
                weight = 1.0 / max(float(np.linalg.norm(b.centre)), cfg.near_range) ** 2
                seen.setdefault(b.instance_id, []).append(Contribution(
                    r.target, b.transformed(to_reference[r.target]), e, weight, c if np.isfinite(c) else 0.0))
    fused = []
    for iid, items in sorted(seen.items()):
        if len(items) < max(cfg.min_targets, 2):
            continue
        confidences = np.array([c.confidence for c in items])
        rescored = rescore is not None and crossed(np.array([c.box.yaw for c in items]), cfg.axis_gate_deg)
        if rescored:
            confidences = np.asarray(rescore([c.box for c in items], [c.target for c in items]), dtype=np.float64)
        out = fuse_boxes([c.box for c in items], cfg.gate, np.array([c.evidence for c in items]), min_evidence,
                         np.array([c.weight for c in items]), cfg.axis_gate_deg, confidences, rescored)
        if out is None or out[1].sum() < cfg.min_targets:
            continue
        box, inliers = out
        kept = [c for c, k in zip(items, inliers) if k]
        spread = float(max(np.linalg.norm(c.box.centre - box.centre) for c in kept))
        fused.append(FusedCar(iid, box, tuple(c.target for c in kept),
                              tuple(c.target for c, k in zip(items, inliers) if not k), spread))
    return fused


def labels_in_frame(boxes: list[Box3D], scores: list[float], cam_to_opt: np.ndarray, K: np.ndarray,
                    image_size: tuple[int, int], dt: float) -> list[KittiLabel]:
    """KITTI labels of ``boxes`` (optimisation frame, target time) in a frame whose camera is
    ``cam_to_opt`` and time is ``dt`` frames after the target's: each box moved by its velocity
    (dynamic ones), put into the camera, with the exact 2D projection through the full pose; boxes
    that project outside the image get no label."""
    world_to_cam = np.linalg.inv(cam_to_opt)
    labels = []
    for b, score in zip(boxes, scores):
        b2 = box_to_2d(b, K, world_to_cam=world_to_cam, image_size=image_size, dt=dt)
        if b2 is not None:
            labels.append(label_from_box(b.at_offset(dt).transformed(world_to_cam), b2, score=float(score)))
    return labels


class MaskBoxes:
    """The tight boxes of a sequence's car masks, each frame's instance map read once:
    ``mask_boxes(frame, instance_id)`` is the box ``(x1, y1, x2, y2)`` or None."""

    def __init__(self, seq: Sequence):
        self.seq = seq
        self._frames: dict[int, dict[int, np.ndarray]] = {}

    def __call__(self, frame: int, instance_id: int) -> np.ndarray | None:
        if frame not in self._frames:
            m = self.seq.instance_map(frame)
            self._frames[frame] = {int(v): tight_box(m == v) for v in car_values(m)}
        return self._frames[frame].get(int(instance_id))


def mask_confidence(box: Box3D, seq: Sequence, frames: list[int], reference: np.ndarray,
                    mask_boxes: MaskBoxes) -> float:
    """docs/method.md §7's confidence of one parked box with a known instance id: mean over ``frames``
    of the 2D IoU of its projection and the instance's mask box (0 without either).
    ``reference`` maps the world to the box's frame; ``mask_boxes``: the sequence's mask boxes."""
    ious = []
    size = seq.calibration.image_size
    for f in frames:
        proj = box_to_2d(box, seq.calibration.K, world_to_cam=np.linalg.inv(reference @ seq.cam0_to_world(f)),
                         image_size=size)
        mask = mask_boxes(f, box.instance_id)
        ious.append(0.0 if proj is None or mask is None else float(iou_matrix(proj[None], mask[None])[0, 0]))
    return float(np.mean(ious)) if ious else 0.0


def apply_consensus(seq_dir: str | Path, seq: Sequence, cfg: ConsensusConfig,
                    heading: HeadingConfig = HeadingConfig()) -> dict:
    """Fuse the parked cars of every finished target under ``seq_dir`` and rewrite the labels of
    the groups they appear in (atomically); write ``seq_dir/consensus.json``, and record the
    rewritten files in the batch manifest where there is one (so that a rerun of the batch still
    finds the targets finished). Returns the consensus report.

    With ``cfg.enabled`` false, groups an earlier consensus rewrote get their targets' own
    boxes back. Damaged target results are reported (``skipped``) and left out, never fatal.
    """
    seq_dir = Path(seq_dir)
    results, skipped = [], []
    for path in sorted((seq_dir / "boxes").glob("*.json")):
        try:
            results.append(TargetBoxes.read(path))
        except DataError as exc:
            skipped.append(str(exc))
    report: dict = {"enabled": cfg.enabled, "config": dataclasses.asdict(cfg), "targets": [r.target for r in results], "skipped": skipped,
                    "reference_target": results[0].target if results else None, "fused": [], "labels_rewritten": []}
    previous = _previously_fused(seq_dir / "consensus.json")
    if not results:
        atomic_write_json(seq_dir / "consensus.json", report)
        return report
    opt = {r.target: opt_from_world(seq.cam0_to_world(r.target)) for r in results}
    reference = opt[results[0].target]
    to_ref = {t: reference @ np.linalg.inv(T) for t, T in opt.items()}
    group_of = {r.target: r.group for r in results}
    mask_boxes = MaskBoxes(seq)

    def confidences(boxes: list[Box3D], targets: list[int]) -> np.ndarray:
        frames = sorted({f for t in targets for f in group_of[t]})
        return np.array([mask_confidence(b, seq, frames, reference, mask_boxes) for b in boxes])

    fused = fuse_parked_cars(results, to_ref, cfg, heading.min_evidence, confidences) if cfg.enabled else []
    fused = [FusedCar(c.instance_id, c.box, c.targets, c.outliers, c.spread,
                      float(confidences([c.box], list(c.targets))[0]))
             for c in fused]
    by_target: dict[int, dict[int, FusedCar]] = {}
    for c in fused:
        for t in c.targets:
            by_target.setdefault(t, {})[c.instance_id] = c
    K, size = seq.calibration.K, seq.calibration.image_size
    for r in results:
        mine = by_target.get(r.target, {})
        if not mine and previous is not None and r.target not in previous:  # still the target's own
            continue
        from_ref = np.linalg.inv(to_ref[r.target])
        boxes, scores = [], []
        for b, score in zip(r.boxes, r.confidences):
            c = mine.get(b.instance_id) if not b.dynamic else None
            boxes.append(b if c is None else c.box.transformed(from_ref))
            scores.append(score if c is None else c.confidence)
        for f in r.group:
            cam_to_opt = opt[r.target] @ seq.cam0_to_world(f)
            rel = f"labels/{f:010d}.txt"
            write_labels(seq_dir / rel, labels_in_frame(boxes, scores, cam_to_opt, K, size, float(f - r.target)))
            report["labels_rewritten"].append(rel)
    report["fused"] = [c.to_dict() for c in fused]
    atomic_write_json(seq_dir / "consensus.json", report)
    if report["labels_rewritten"] and (seq_dir / MANIFEST_NAME).is_file():
        # the batch's record of these files must follow them, or a rerun redoes every target
        with Manifest(seq_dir, seq.name) as manifest:
            manifest.refresh_outputs(report["labels_rewritten"])
    return report


def _previously_fused(path: Path) -> set[int] | None:
    """Targets whose labels an earlier consensus rewrote (they are rewritten again, fused or not);
    None (all of them) when the record is damaged."""
    if not path.is_file():
        return set()
    try:
        return {int(t) for car in json.loads(path.read_text()).get("fused", []) for t in car["targets"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
