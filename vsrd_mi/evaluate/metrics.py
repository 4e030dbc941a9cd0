"""Box-quality statistics of one-to-one matched (prediction, ground truth) pairs.

Per frame, predictions and ground truth are paired by the Hungarian algorithm
(:func:`scipy.optimize.linear_sum_assignment`) maximising the total 3D IoU; a pair counts as
matched when its 3D IoU exceeds ``min_iou`` (0 by default: the boxes overlap at all). Reported,
for all ground truth and split into static / dynamic (the ground truth's ``dynamic`` flag):

* ``mean_iou_bev`` / ``mean_iou_3d``: mean IoU over matched pairs;
* ``recall_weighted_iou_bev`` / ``recall_weighted_iou_3d``: the same sums divided by the number of
  ground-truth boxes, i.e. every unmatched ground-truth box counts as IoU 0;
* ``centre_error_m``: mean Euclidean distance of the box centres (metres);
* ``yaw_error_deg``: mean yaw difference modulo 180 degrees (a box turned by 180 degrees is the same
  box, so the error is in [0, 90]; the heading's direction is not judged);
* ``size_error_m``: mean absolute error of the full (w, h, l) extents (metres), per axis.

Means over no pairs are None.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..geometry.boxes import Box3D, wrap_angle
from ..geometry.iou3d import iou_matrices

#: Names of the ground-truth groups in the statistics.
GROUP_ALL, GROUP_STATIC, GROUP_DYNAMIC = "all", "static", "dynamic"
GROUPS = (GROUP_ALL, GROUP_STATIC, GROUP_DYNAMIC)


@dataclass(frozen=True)
class MatchedPair:
    """A ground-truth box, its matched prediction and their IoUs."""

    gt: Box3D
    pred: Box3D
    iou_bev: float
    iou_3d: float


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
    d = abs(float(wrap_angle(a - b)))
    return min(d, np.pi - d)


@dataclass
class PairStatistics:
    """Accumulates matched pairs and ground-truth counts per group (see the module docstring)."""

    n_gt: dict[str, int] = field(default_factory=lambda: {g: 0 for g in GROUPS})
    pairs: dict[str, list[MatchedPair]] = field(default_factory=lambda: {g: [] for g in GROUPS})

    @staticmethod
    def _groups(box: Box3D) -> tuple[str, str]:
        return GROUP_ALL, GROUP_DYNAMIC if box.dynamic else GROUP_STATIC

    def add_frame(self, gt: Sequence[Box3D], pred: Sequence[Box3D], gt_counted: Sequence[bool],
                  min_iou: float = 0.0) -> None:
        """Match one frame; ground truth with ``gt_counted`` False is matched but not reported."""
        for box, counted in zip(gt, gt_counted):
            if counted:
                for g in self._groups(box):
                    self.n_gt[g] += 1
        for i, j, iou_bev, iou_3d in hungarian_pairs(gt, pred, min_iou):
            if gt_counted[i]:
                for g in self._groups(gt[i]):
                    self.pairs[g].append(MatchedPair(gt[i], pred[j], iou_bev, iou_3d))

    def summary(self) -> dict[str, dict]:
        """Per group: counts, mean / recall-weighted IoUs and mean errors (JSON-ready)."""
        out = {}
        for g in GROUPS:
            pairs, n_gt = self.pairs[g], self.n_gt[g]
            bev = np.array([p.iou_bev for p in pairs])
            iou3d = np.array([p.iou_3d for p in pairs])
            centre = np.array([np.linalg.norm(p.pred.centre - p.gt.centre) for p in pairs])
            yaw = np.degrees([yaw_error_mod_pi(p.pred.yaw, p.gt.yaw) for p in pairs])
            size = np.array([np.abs(p.pred.size - p.gt.size) for p in pairs]).reshape(-1, 3)
            out[g] = {
                "n_gt": n_gt,
                "n_matched": len(pairs),
                "mean_iou_bev": _mean(bev),
                "mean_iou_3d": _mean(iou3d),
                "recall_weighted_iou_bev": float(bev.sum() / n_gt) if n_gt else None,
                "recall_weighted_iou_3d": float(iou3d.sum() / n_gt) if n_gt else None,
                "centre_error_m": _mean(centre),
                "yaw_error_deg": _mean(yaw),
                "size_error_m": ({"w": float(size[:, 0].mean()), "h": float(size[:, 1].mean()),
                                  "l": float(size[:, 2].mean())} if len(pairs) else None),
            }
        return out


def _mean(values: np.ndarray) -> float | None:
    return float(np.mean(values)) if len(values) else None
