"""Box-quality statistics of one-to-one matched (prediction, ground truth) pairs, and breakdowns.

Per frame, predictions and ground truth are paired by the Hungarian algorithm
(:func:`scipy.optimize.linear_sum_assignment`) maximising the total 3D IoU; a pair counts as
matched when its 3D IoU exceeds ``min_iou`` (0 by default: the boxes overlap at all). Every counted
ground-truth car becomes a :class:`GroundTruthRecord` (matched or not); :func:`summarise` reports,
for any list of records:

* ``n_gt``, ``n_matched`` and ``missed_share``: the share of the cars left without a box;
* ``n_cars``: how many distinct cars the records are of (a car counts once however many frames
  see it: ``(sequence, instance id)``; records without an instance id, a negative one, count one
  each). A figure over many records of few cars varies from one set of streets to the next as
  the cars do;
* ``mean_iou_bev`` / ``mean_iou_3d``: mean IoU over matched pairs;
* ``recall_weighted_iou_bev`` / ``recall_weighted_iou_3d``: the same sums divided by ``n_gt``,
  i.e. every unmatched ground-truth box counts as IoU 0;
* ``centre_error_m``: mean Euclidean distance of the box centres (metres);
* ``yaw_error_deg`` / ``yaw_error_median_deg``: mean / median yaw difference modulo 180 degrees
  (a box turned end for end has the same axis; in [0, 90]);
* ``heading_accuracy``: share of matched pairs whose heading is right, ``|yaw error| < 90`` deg
  on the full circle (front and back told apart);
* ``size_error_m``: mean absolute error of the full (w, h, l) extents (metres), per axis;
* ``size_bias``: signed error prediction - truth of ``length``, ``width``, ``height``, each with
  ``mean_m``, ``median_m`` (metres), ``mean_rel``, ``median_rel`` (relative to the truth) and
  ``mean_rel_ci95``: a 95 % interval of ``mean_rel`` from resampling the *cars* (a cluster
  bootstrap, :func:`car_interval`): the records of one car share its error (a parked car's fused
  box is written into every frame that sees it), so a class of 30 records may hold 5 cars and
  its mean moves with them; ``n_cars`` says how many matched cars it resamples. A percentile
  bootstrap over few clusters is too narrow: with 3-7 cars such an interval holds the true mean
  in roughly 70-85 % of samples, not 95 %.

:class:`PairStatistics` collects the records of a sequence and splits them by ground truth
(static / dynamic) and, in :meth:`PairStatistics.breakdowns`, by vehicle class, distance,
occlusion and parking kind (:mod:`.attributes`), and by whether a view that labels the car sees
its length, also by class over the cars whose length is seen (:mod:`.observability`). Means over
no pairs are None.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..geometry.boxes import Box3D, axis_difference, wrap_angle
from ..geometry.iou3d import iou_matrices
from .attributes import UNKNOWN, CarAttributes

#: Names of the ground-truth groups in the statistics.
GROUP_ALL, GROUP_STATIC, GROUP_DYNAMIC = "all", "static", "dynamic"
GROUPS = (GROUP_ALL, GROUP_STATIC, GROUP_DYNAMIC)

#: A heading is right when the full-circle yaw error is below this (degrees): front and back
#: are told apart, any smaller error is an error of the axis.
HEADING_RIGHT_DEG = 90.0

#: Names and ``Box3D.size`` indices of the three extents in the size bias.
EXTENTS = (("length", 2), ("width", 0), ("height", 1))

#: The size bias's interval over cars (:func:`car_interval`): coverage, resamples of the cars and
#: the resampler's seed (fixed, so that a rerun reports the same interval).
INTERVAL_LEVEL = 0.95
INTERVAL_RESAMPLES = 2000
INTERVAL_SEED = 0


@dataclass(frozen=True)
class MatchedPair:
    """A ground-truth box, its matched prediction and their IoUs."""

    gt: Box3D
    pred: Box3D
    iou_bev: float
    iou_3d: float


@dataclass(frozen=True)
class GroundTruthRecord:
    """A counted ground-truth car of one frame, its attributes and its match (None: missed)."""

    frame: int
    gt: Box3D
    attributes: CarAttributes = UNKNOWN
    pred: Box3D | None = None
    iou_bev: float = 0.0
    iou_3d: float = 0.0
    #: The sequence the frame belongs to (with the instance id it names the car across frames).
    sequence: str = ""

    @property
    def matched(self) -> bool:
        return self.pred is not None

    @property
    def distance_m(self) -> float:
        """Horizontal distance of the car's centre from the camera (metres, x-z plane)."""
        return float(np.hypot(self.gt.centre[0], self.gt.centre[2]))


def hungarian_pairs(gt: Sequence[Box3D], pred: Sequence[Box3D], min_iou: float = 0.0
                    ) -> list[tuple[int, int, float, float]]:
    """One-to-one pairs ``(gt index, pred index, BEV IoU, 3D IoU)`` maximising the summed 3D IoU.

    Only pairs with 3D IoU > ``min_iou`` are returned.
    """
    if len(gt) == 0 or len(pred) == 0:
        return []
    bev, iou3d = iou_matrices(gt, pred)
    rows, cols = linear_sum_assignment(-iou3d)
    return [(int(i), int(j), float(bev[i, j]), float(iou3d[i, j]))
            for i, j in zip(rows, cols) if iou3d[i, j] > min_iou]


def yaw_error_mod_pi(a: float, b: float) -> float:
    """Absolute yaw difference modulo pi, in radians, in ``[0, pi/2]``."""
    return float(axis_difference(a, b))


def heading_error(a: float, b: float) -> float:
    """Absolute yaw difference on the full circle, in radians, in ``[0, pi]``."""
    return abs(float(wrap_angle(a - b)))


def match_frame(frame: int, gt: Sequence[Box3D], pred: Sequence[Box3D], gt_counted: Sequence[bool],
                min_iou: float = 0.0, attributes: Sequence[CarAttributes] | None = None,
                sequence: str = "") -> list[GroundTruthRecord]:
    """Records of the counted ground truth of one frame of ``sequence`` (all ground truth takes
    part in the Hungarian matching; ground truth with ``gt_counted`` False is matched but not
    recorded)."""
    attributes = list(attributes) if attributes is not None else [UNKNOWN] * len(gt)
    if len(attributes) != len(gt):
        raise ValueError(f"frame {frame}: {len(gt)} ground-truth boxes but {len(attributes)} attributes")
    matches = {i: (j, bev, iou3d) for i, j, bev, iou3d in hungarian_pairs(gt, pred, min_iou)}
    records = []
    for i, (box, counted) in enumerate(zip(gt, gt_counted)):
        if not counted:
            continue
        if i in matches:
            j, bev, iou3d = matches[i]
            records.append(GroundTruthRecord(frame, box, attributes[i], pred[j], bev, iou3d, sequence))
        else:
            records.append(GroundTruthRecord(frame, box, attributes[i], sequence=sequence))
    return records


def _mean(values) -> float | None:
    return float(np.mean(values)) if len(values) else None


def _median(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def heading_accuracy(records: Sequence[GroundTruthRecord]) -> float | None:
    """Share of the matched records whose heading is right (see :data:`HEADING_RIGHT_DEG`)."""
    errors = [np.degrees(heading_error(r.pred.yaw, r.gt.yaw)) for r in records if r.matched]
    return float(np.mean(np.array(errors) < HEADING_RIGHT_DEG)) if errors else None


def size_bias(records: Sequence[GroundTruthRecord]) -> dict[str, dict] | None:
    """Signed size error (prediction - truth) of the matched records per extent (see module)."""
    matched = [r for r in records if r.matched]
    if not matched:
        return None
    pred = np.array([r.pred.size for r in matched])
    gt = np.array([r.gt.size for r in matched])
    cars = car_labels(matched)
    out: dict = {"n_cars": len(set(cars.tolist()))}
    for name, axis in EXTENTS:
        diff = pred[:, axis] - gt[:, axis]
        rel = diff / gt[:, axis]
        out[name] = {"mean_m": float(diff.mean()), "median_m": float(np.median(diff)),
                     "mean_rel": float(rel.mean()), "median_rel": float(np.median(rel)),
                     "mean_rel_ci95": list(car_interval(rel, cars))}
    return out


def car_labels(records: Sequence[GroundTruthRecord]) -> np.ndarray:
    """One integer per record naming its car: equal for the records of one ``(sequence, instance
    id)``, distinct for every record whose ground truth has no instance id (a negative one,
    :class:`Box3D`'s default)."""
    keys = [(r.sequence, r.gt.instance_id) if r.gt.instance_id >= 0 else ("", -1 - k)
            for k, r in enumerate(records)]
    index: dict[tuple, int] = {}
    return np.array([index.setdefault(key, len(index)) for key in keys], dtype=np.int64)


def car_count(records: Sequence[GroundTruthRecord]) -> int:
    """Distinct cars among ``records`` (:func:`car_labels`)."""
    return len(set(car_labels(records).tolist())) if records else 0


def car_interval(values: np.ndarray, cars: np.ndarray, level: float = INTERVAL_LEVEL,
                 resamples: int = INTERVAL_RESAMPLES, seed: int = INTERVAL_SEED) -> tuple[float, float]:
    """Percentile interval of the mean of ``values`` over records, when whole cars are resampled.

    ``cars`` (same length) names each record's car (:func:`car_labels`). Each resample draws as
    many cars as there are, with replacement, and takes the mean over all their records (the
    statistic's own weighting: a car counts once per record). With one car the interval is that
    car's mean: it has no width because nothing is known of the spread between cars.
    """
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    cars = np.asarray(cars).reshape(-1)
    if values.size == 0 or values.size != cars.size:
        raise ValueError(f"car_interval: need as many car labels as values (> 0), got {cars.size} and {values.size}")
    if not 0.0 < level < 1.0 or resamples < 1:
        raise ValueError(f"car_interval: level must be in (0, 1) and resamples >= 1, got {level}, {resamples}")
    _, label = np.unique(cars, return_inverse=True)
    sums = np.bincount(label, weights=values)
    counts = np.bincount(label).astype(np.float64)
    draws = np.random.default_rng(seed).integers(0, len(sums), size=(resamples, len(sums)))
    means = sums[draws].sum(axis=1) / counts[draws].sum(axis=1)
    tail = 50.0 * (1.0 - level)
    lo, hi = np.percentile(means, [tail, 100.0 - tail])
    return float(lo), float(hi)


def summarise(records: Sequence[GroundTruthRecord]) -> dict:
    """Counts, IoUs and errors of ``records`` (JSON-ready; see the module docstring)."""
    matched = [r for r in records if r.matched]
    n_gt = len(records)
    bev = np.array([r.iou_bev for r in matched])
    iou3d = np.array([r.iou_3d for r in matched])
    centre = [float(np.linalg.norm(r.pred.centre - r.gt.centre)) for r in matched]
    yaw = np.degrees([yaw_error_mod_pi(r.pred.yaw, r.gt.yaw) for r in matched])
    size = np.array([np.abs(r.pred.size - r.gt.size) for r in matched]).reshape(-1, 3)
    return {
        "n_gt": n_gt,
        "n_cars": car_count(records),
        "n_matched": len(matched),
        "missed_share": (n_gt - len(matched)) / n_gt if n_gt else None,
        "mean_iou_bev": _mean(bev),
        "mean_iou_3d": _mean(iou3d),
        "recall_weighted_iou_bev": float(bev.sum() / n_gt) if n_gt else None,
        "recall_weighted_iou_3d": float(iou3d.sum() / n_gt) if n_gt else None,
        "centre_error_m": _mean(centre),
        "yaw_error_deg": _mean(yaw),
        "yaw_error_median_deg": _median(yaw),
        "heading_accuracy": heading_accuracy(records),
        "size_error_m": ({"w": float(size[:, 0].mean()), "h": float(size[:, 1].mean()),
                          "l": float(size[:, 2].mean())} if len(matched) else None),
        "size_bias": size_bias(records),
    }


def bin_labels(edges: Sequence[float], unit: str = "", scale: float = 1.0) -> list[str]:
    """Labels ``"a-b"`` of the bins ``[edges[k], edges[k+1])`` and ``"last+"`` of the open last one."""
    fmt = [f"{e * scale:g}" for e in edges]
    return [f"{a}-{b}{unit}" for a, b in zip(fmt[:-1], fmt[1:])] + [f"{fmt[-1]}{unit}+"]


def bin_of(value: float | None, edges: Sequence[float], labels: Sequence[str]) -> str | None:
    """Label of the bin holding ``value`` (None below the first edge or when ``value`` is None)."""
    if value is None or value < edges[0]:
        return None
    return labels[int(np.searchsorted(edges, value, side="right")) - 1]


def breakdown(records: Sequence[GroundTruthRecord], key: Callable[[GroundTruthRecord], str | None],
              order: Sequence[str] | None = None) -> dict[str, dict] | None:
    """:func:`summarise` per value of ``key(record)`` (records with key None are left out);
    None when no record has a key. Groups appear in ``order`` first, then sorted."""
    groups: dict[str, list[GroundTruthRecord]] = {}
    for r in records:
        k = key(r)
        if k is not None:
            groups.setdefault(k, []).append(r)
    if not groups:
        return None
    names = [n for n in (order or ()) if n in groups] + sorted(n for n in groups if n not in (order or ()))
    return {n: summarise(groups[n]) for n in names}


#: A view sees a car's length when moving its far end out by the probe moves its 2D box by at
#: least this much (px, :mod:`vsrd_mi.evaluate.observability`): one pixel of a mask.
LENGTH_SEEN_PX = 1.0
#: Groups of the ``by_length_view`` breakdown: some view that labels the car sees its length, or
#: none does.
LENGTH_SEEN, LENGTH_NOT_SEEN = "seen", "not seen"
LENGTH_VIEW_GROUPS = (LENGTH_SEEN, LENGTH_NOT_SEEN)


def length_view_group(record: GroundTruthRecord) -> str | None:
    """:data:`LENGTH_SEEN` when the record's ``length_view_px`` reaches :data:`LENGTH_SEEN_PX`,
    :data:`LENGTH_NOT_SEEN` below it, None where it was not measured."""
    shift = record.attributes.length_view_px
    if shift is None:
        return None
    return LENGTH_SEEN if shift >= LENGTH_SEEN_PX else LENGTH_NOT_SEEN


@dataclass(frozen=True)
class BreakdownBins:
    """Bin edges of the distance and occlusion breakdowns (the last bin is open-ended)."""

    #: Horizontal distance of the car's centre from the camera, metres.
    distance_m: tuple[float, ...] = (0.0, 20.0, 40.0, 60.0)
    #: Occlusion ``1 - visible / amodal`` pixels (sidecar only), as a fraction.
    occlusion: tuple[float, ...] = (0.0, 0.3, 0.6, 0.8)


@dataclass
class PairStatistics:
    """Accumulates the :class:`GroundTruthRecord` of every evaluated frame."""

    records: list[GroundTruthRecord] = field(default_factory=list)

    def add_frame(self, gt: Sequence[Box3D], pred: Sequence[Box3D], gt_counted: Sequence[bool],
                  min_iou: float = 0.0, attributes: Sequence[CarAttributes] | None = None,
                  frame: int = 0, sequence: str = "") -> None:
        """Match one frame of ``sequence`` (:func:`match_frame`) and keep its records."""
        self.records += match_frame(frame, gt, pred, gt_counted, min_iou, attributes, sequence)

    def summary(self) -> dict[str, dict]:
        """:func:`summarise` of all records and of the static / dynamic ground truth."""
        dynamic = [r for r in self.records if r.gt.dynamic]
        static = [r for r in self.records if not r.gt.dynamic]
        return {GROUP_ALL: summarise(self.records), GROUP_STATIC: summarise(static),
                GROUP_DYNAMIC: summarise(dynamic)}

    def breakdowns(self, bins: BreakdownBins = BreakdownBins()) -> dict[str, dict | None]:
        """:func:`summarise` by vehicle class, distance, occlusion, parking kind and whether the
        length is seen (:func:`length_view_group`; and by class over the records whose length is
        seen). A breakdown whose attribute no record has (e.g. no sidecar) is None.
        """
        distance_labels = bin_labels(bins.distance_m, " m")
        occlusion_labels = bin_labels(bins.occlusion, " %", 100.0)
        return {
            "by_class": breakdown(self.records, lambda r: r.attributes.vehicle_class),
            "by_distance": breakdown(self.records, lambda r: bin_of(r.distance_m, bins.distance_m,
                                                                     distance_labels), distance_labels),
            "by_occlusion": breakdown(self.records, lambda r: bin_of(r.attributes.occlusion, bins.occlusion,
                                                                      occlusion_labels), occlusion_labels),
            "by_parking": breakdown(self.records, lambda r: r.attributes.parking),
            "by_length_view": breakdown(self.records, length_view_group, LENGTH_VIEW_GROUPS),
            "by_class_length_seen": breakdown(
                [r for r in self.records if length_view_group(r) == LENGTH_SEEN],
                lambda r: r.attributes.vehicle_class),
        }
