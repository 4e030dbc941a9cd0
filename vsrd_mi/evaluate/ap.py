"""KITTI average precision with 41-point recall sampling: AP|R40 and AP|R11.

Two precision curves are computed from the same devkit matching (:mod:`.matching`):

``exact`` (the headline numbers)
    (recall, precision) at *every* distinct detection score used as threshold, so the curve has
    a point wherever it changes. Interpolated (monotone) precision at recall ``r`` is the highest
    precision of any point with recall >= ``r`` (0 when no point reaches ``r``), sampled at
    ``r = k / 40``, ``k = 0..40``. AP|R40 averages ``k = 1..40`` (Simonelli et al. 2019), AP|R11
    averages ``k = 0, 4, ..., 40`` (recall 0, 0.1, ..., 1).

``devkit`` (comparability with published numbers)
    The official devkit's shortcut: from the sorted true-positive scores of the first pass it keeps
    at most 41 thresholds, the score whose recall is nearest to each step ``k / 40`` (always keeping
    the last true positive), and assigns the precision at the ``k``-th kept threshold to sample
    ``k``; missing samples are 0; precision is made monotone over the samples. Rounding to the
    nearest recall makes it read up to ~2 AP above the exact curve on large sets; with fewer than
    41 counted ground-truth boxes the assignment is shifted by one sample, so even perfect
    detections score below 100 (e.g. 97.5 AP|R40 with exactly 40 ground-truth boxes).

Recall is TP / (number of counted ground-truth boxes), the denominator the devkit's recall sampling
uses (a counted box matched by an ignored detection is neither TP nor FN, so it only lowers the
reachable recall). A precision of 0/0 (no counted detection above a threshold) is taken as 0. With
no counted ground truth AP is undefined and reported as None.

AOS (average orientation similarity, Geiger et al. 2012) replaces the precision ``TP / (TP + FP)``
by ``sum over TPs of (1 + cos(alpha_gt - alpha_det)) / 2`` divided by ``TP + FP`` at the same
thresholds, and is sampled and averaged exactly like AP on both curves, so AOS <= AP and AOS = AP
when every true positive's observation angle is right. The devkit pairs AOS with its 2D-box
matching; here it comes with each BEV / 3D matching and threshold.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .matching import FP, N_COUNTS, SIM, TP, FrameMatchInput, frame_threshold_events, match_true_positive_scores

#: Number of recall samples of the KITTI protocol (recall 0, 1/40, ..., 1).
N_RECALL_SAMPLES = 41
#: Samples averaged by AP|R11 are every ``R11_STRIDE``-th (recall 0, 0.1, ..., 1.0).
R11_STRIDE = 4
#: APs are reported in percent.
AP_SCALE = 100.0

#: Names of the two precision curves, as they appear in results.
CURVE_EXACT = "exact"
CURVE_DEVKIT = "devkit"

CURVE_DESCRIPTIONS = {
    CURVE_EXACT: ("exact curve: precision/recall at every distinct detection score (devkit "
                  "matching at each threshold), monotone precision max_{recall' >= r}, sampled at "
                  "r = k/40"),
    CURVE_DEVKIT: ("KITTI devkit curve: precision at <= 41 thresholds picked from the true-positive "
                   "scores by nearest recall (keeps the last TP score), k-th threshold -> sample k, "
                   "monotone over samples"),
}


@dataclass(frozen=True)
class APResult:
    """AP and AOS (percent) of one metric / IoU threshold / difficulty, for both precision curves.

    ``precision_*`` and ``orientation_*`` hold the 41 monotone precision and orientation-similarity
    samples; ``n_gt`` is the number of counted ground-truth boxes; ``max_recall`` the recall with
    every detection kept.
    """

    n_gt: int
    max_recall: float
    precision_exact: np.ndarray
    precision_devkit: np.ndarray
    orientation_exact: np.ndarray
    orientation_devkit: np.ndarray

    @staticmethod
    def _r40(p: np.ndarray) -> float:
        return float(AP_SCALE * p[1:].mean())

    @staticmethod
    def _r11(p: np.ndarray) -> float:
        return float(AP_SCALE * p[::R11_STRIDE].mean())

    @property
    def r40(self) -> float | None:
        """AP|R40 of the exact curve (None without counted ground truth)."""
        return self._r40(self.precision_exact) if self.n_gt else None

    @property
    def r11(self) -> float | None:
        """AP|R11 of the exact curve (None without counted ground truth)."""
        return self._r11(self.precision_exact) if self.n_gt else None

    @property
    def devkit_r40(self) -> float | None:
        """AP|R40 of the devkit curve (None without counted ground truth)."""
        return self._r40(self.precision_devkit) if self.n_gt else None

    @property
    def devkit_r11(self) -> float | None:
        """AP|R11 of the devkit curve (None without counted ground truth)."""
        return self._r11(self.precision_devkit) if self.n_gt else None

    @property
    def aos_r40(self) -> float | None:
        """AOS|R40 of the exact curve (None without counted ground truth)."""
        return self._r40(self.orientation_exact) if self.n_gt else None

    @property
    def aos_r11(self) -> float | None:
        """AOS|R11 of the exact curve (None without counted ground truth)."""
        return self._r11(self.orientation_exact) if self.n_gt else None

    @property
    def devkit_aos_r40(self) -> float | None:
        """AOS|R40 of the devkit curve (None without counted ground truth)."""
        return self._r40(self.orientation_devkit) if self.n_gt else None

    @property
    def devkit_aos_r11(self) -> float | None:
        """AOS|R11 of the devkit curve (None without counted ground truth)."""
        return self._r11(self.orientation_devkit) if self.n_gt else None

    def to_dict(self) -> dict:
        return {"R40": self.r40, "R11": self.r11, "devkit_R40": self.devkit_r40,
                "devkit_R11": self.devkit_r11, "AOS_R40": self.aos_r40, "AOS_R11": self.aos_r11,
                "devkit_AOS_R40": self.devkit_aos_r40, "devkit_AOS_R11": self.devkit_aos_r11,
                "n_gt": self.n_gt, "max_recall": self.max_recall}


def devkit_thresholds(tp_scores: Sequence[float], n_gt: int,
                      n_samples: int = N_RECALL_SAMPLES) -> list[float]:
    """The devkit's ``getThresholds``: TP scores nearest to each recall step ``k / (n_samples - 1)``.

    At most ``n_samples`` thresholds result (a kept non-last score has recall below 1, so at most
    ``n_samples - 1`` of them precede the always-kept last one).
    """
    scores = sorted(tp_scores, reverse=True)
    thresholds: list[float] = []
    current_recall = 0.0
    for i, score in enumerate(scores):
        last = i == len(scores) - 1
        l_recall = (i + 1) / n_gt
        r_recall = l_recall if last else (i + 2) / n_gt
        if (r_recall - current_recall) < (current_recall - l_recall) and not last:
            continue
        thresholds.append(score)
        current_recall += 1.0 / (n_samples - 1.0)
    return thresholds


def _ratio(numerator: np.ndarray, tp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``numerator / (tp + fp)`` with 0/0 taken as 0 (precision: ``numerator = tp``; AOS: the
    summed orientation similarity)."""
    denom = tp + fp
    return np.where(denom > 0, numerator / np.maximum(denom, 1), 0.0)


def _exact_samples(tp: np.ndarray, precision: np.ndarray, n_gt: int) -> np.ndarray:
    """Monotone precision at recall ``k / 40`` from curve points with ``tp`` true positives."""
    steps = N_RECALL_SAMPLES - 1
    tp = np.rint(tp).astype(np.int64)
    out = np.zeros(N_RECALL_SAMPLES)
    for k in range(N_RECALL_SAMPLES):
        reach = tp * steps >= k * n_gt  # recall >= k / steps, in exact integer arithmetic
        if np.any(reach):
            out[k] = precision[reach].max()
    return out


def _devkit_samples(values: np.ndarray) -> np.ndarray:
    """The devkit's samples: value at the k-th kept threshold for sample k (0 beyond the last),
    made monotone (maximum over the later samples)."""
    p = np.zeros(N_RECALL_SAMPLES)
    p[:len(values)] = values
    return np.maximum.accumulate(p[::-1])[::-1]


def average_precision(frames: Sequence[FrameMatchInput], min_overlap: float) -> APResult:
    """AP of detections against ground truth over ``frames`` at overlap > ``min_overlap``."""
    n_gt = sum(f.n_counted_gt for f in frames)
    levels, deltas = [np.empty(0)], [np.empty((0, N_COUNTS))]
    tp_scores: list[float] = []
    for f in frames:
        lv, dl = frame_threshold_events(f, min_overlap)
        levels.append(lv)
        deltas.append(dl)
        tp_scores += match_true_positive_scores(f, min_overlap)
    all_levels, all_deltas = np.concatenate(levels), np.concatenate(deltas)
    order = np.argsort(all_levels, kind="stable")
    sorted_levels = all_levels[order]
    # suffix[k] = sum of the deltas of events k.. (ascending score order); suffix[E] = 0.
    suffix = np.concatenate([np.cumsum(all_deltas[order][::-1], axis=0)[::-1], np.zeros((1, N_COUNTS))])
    base = np.array([0.0, 0.0, n_gt, 0.0])

    def counts(thresholds: np.ndarray) -> np.ndarray:
        """Sequence-wide (TP, FP, FN, similarity), shape (T, 4), keeping detections with
        score >= threshold."""
        return base + suffix[np.searchsorted(sorted_levels, thresholds, side="left")]

    zeros = np.zeros(N_RECALL_SAMPLES)
    precision_exact, precision_devkit, orientation_exact, orientation_devkit = zeros, zeros, zeros, zeros
    max_recall = 0.0
    if n_gt > 0 and len(sorted_levels) > 0:
        c = counts(np.unique(sorted_levels))
        precision_exact = _exact_samples(c[:, TP], _ratio(c[:, TP], c[:, TP], c[:, FP]), n_gt)
        orientation_exact = _exact_samples(c[:, TP], _ratio(c[:, SIM], c[:, TP], c[:, FP]), n_gt)
        max_recall = float(np.rint(c[:, TP].max()) / n_gt)
        thresholds = np.array(devkit_thresholds(tp_scores, n_gt))
        if len(thresholds):
            c = counts(thresholds)
            precision_devkit = _devkit_samples(_ratio(c[:, TP], c[:, TP], c[:, FP]))
            orientation_devkit = _devkit_samples(_ratio(c[:, SIM], c[:, TP], c[:, FP]))
    return APResult(n_gt=n_gt, max_recall=max_recall, precision_exact=precision_exact,
                    precision_devkit=precision_devkit, orientation_exact=orientation_exact,
                    orientation_devkit=orientation_devkit)

