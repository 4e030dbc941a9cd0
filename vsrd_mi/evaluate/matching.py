"""Per-frame detection matching exactly as the KITTI object devkit does it (``evaluate_object.cpp``).

The devkit matches in two kinds of pass over the ground truth of one image, in ground-truth order:

* :func:`match_true_positive_scores` (``computeStatistics(compute_fp=false)``): every ground-truth
  box takes the *highest-scoring* unassigned detection with overlap > ``min_overlap``; the scores of
  the detections matched to counted ground truth are the candidate thresholds of the PR curve.
* :func:`count_at_threshold` (``computeStatistics(compute_fp=true, thresh)``): only detections
  with score >= ``thresh`` take part; every ground-truth box takes the unassigned counted
  detection of *highest overlap* (> ``min_overlap``), or, failing that, the first ignored one.

"Ignored" ground truth (too small for the difficulty) and ignored detections (2D box too small)
may absorb a match but count neither as true positive, false positive nor false negative: a
counted ground-truth box whose match is an ignored detection is no hit and no miss, yet it stays in
the recall denominator (the devkit's ``n_gt`` counts every counted ground-truth box).
(Other classes and DontCare regions of the devkit do not occur: inputs are cars only.)

The counting pass also sums the devkit's orientation similarity ``(1 + cos(alpha_gt - alpha_det)) / 2``
over its true positives (the numerator of AOS, :mod:`vsrd_mi.evaluate.ap`).

:func:`frame_threshold_events` turns one frame's pass results at every score level of that frame
into increments, so that sequence-wide (TP, FP, FN, similarity) at any threshold is a suffix sum
(:mod:`vsrd_mi.evaluate.ap`) instead of a re-run over every frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrameMatchInput:
    """What the matching of one frame needs for one overlap metric and difficulty.

    ``overlap`` is (G, D) (ground truth x detections), ``gt_ignored`` (G,) and ``det_ignored`` (D,)
    booleans, ``scores`` (D,) detection scores, ``similarity`` (G, D) the orientation similarity
    of each pair (:func:`orientation_similarity`; None: zeros, AOS is then 0).
    """

    overlap: np.ndarray
    gt_ignored: np.ndarray
    det_ignored: np.ndarray
    scores: np.ndarray
    similarity: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "gt_ignored", np.asarray(self.gt_ignored, dtype=bool).reshape(-1))
        object.__setattr__(self, "det_ignored", np.asarray(self.det_ignored, dtype=bool).reshape(-1))
        object.__setattr__(self, "scores", np.asarray(self.scores, dtype=np.float64).reshape(-1))
        g, d = len(self.gt_ignored), len(self.det_ignored)
        overlap = np.asarray(self.overlap, dtype=np.float64)
        if overlap.size == 0 and g * d == 0:
            overlap = overlap.reshape(g, d)  # e.g. [] for a frame without ground truth
        object.__setattr__(self, "overlap", overlap)
        if np.shape(self.overlap) != (g, d) or len(self.scores) != d:
            raise ValueError(f"inconsistent shapes: overlap {np.shape(self.overlap)}, "
                             f"{g} ground truth, {d} detections, {len(self.scores)} scores")
        similarity = (np.zeros((g, d)) if self.similarity is None
                      else np.asarray(self.similarity, dtype=np.float64).reshape(g, d))
        object.__setattr__(self, "similarity", similarity)

    @property
    def n_counted_gt(self) -> int:
        """Number of ground-truth boxes that count (are not ignored)."""
        return int(np.count_nonzero(~self.gt_ignored))


@dataclass(frozen=True)
class Counts:
    """True positives, false positives, false negatives and the summed orientation similarity of
    the true positives."""

    tp: int
    fp: int
    fn: int
    similarity: float = 0.0


#: Columns of the per-threshold count arrays: TP, FP, FN (integers held as floats) and the summed
#: orientation similarity of the TPs.
TP, FP, FN, SIM = range(4)
N_COUNTS = 4


def orientation_similarity(alpha_gt: np.ndarray, alpha_det: np.ndarray) -> np.ndarray:
    """The devkit's orientation similarity ``(1 + cos(alpha_gt - alpha_det)) / 2`` of every pair,
    shape (G, D), from observation angles (radians) ``alpha_gt`` (G,) and ``alpha_det`` (D,)."""
    gt = np.asarray(alpha_gt, dtype=np.float64).reshape(-1, 1)
    delta = gt - np.asarray(alpha_det, dtype=np.float64).reshape(1, -1)
    return 0.5 * (1.0 + np.cos(delta))


def match_true_positive_scores(frame: FrameMatchInput, min_overlap: float) -> list[float]:
    """Scores of the true positives of the devkit's first pass (no score threshold)."""
    gt_ignored, det_ignored, scores = frame.gt_ignored, frame.det_ignored, frame.scores
    assigned = np.zeros(len(scores), dtype=bool)
    tp_scores: list[float] = []
    for i in range(len(gt_ignored)):
        candidates = ~assigned & (frame.overlap[i] > min_overlap)
        if not np.any(candidates):
            continue
        j = int(np.argmax(np.where(candidates, scores, -np.inf)))  # first of the best on ties
        assigned[j] = True
        if not gt_ignored[i] and not det_ignored[j]:
            tp_scores.append(float(scores[j]))
    return tp_scores


def counts_at_thresholds(frame: FrameMatchInput, min_overlap: float,
                         thresholds: np.ndarray) -> np.ndarray:
    """(TP, FP, FN, similarity) of one frame, shape (T, 4) float, for each score threshold in
    ``thresholds`` (T,) (columns :data:`TP`, :data:`FP`, :data:`FN`, :data:`SIM`).

    Row ``t`` counts only detections with score >= ``thresholds[t]``; the devkit's sequential pass
    over the ground truth runs once, vectorised over the thresholds.
    """
    thresholds = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    gt_ignored, det_ignored = frame.gt_ignored, frame.det_ignored
    active = frame.scores[None, :] >= thresholds[:, None]  # (T, D)
    above = frame.overlap > min_overlap  # (G, D)
    assigned = np.zeros_like(active)
    tp = np.zeros(len(thresholds), dtype=np.int64)
    fn = np.zeros(len(thresholds), dtype=np.int64)
    sim = np.zeros(len(thresholds))
    rows = np.arange(len(thresholds))
    if len(det_ignored) == 0:
        return np.stack([tp, np.zeros_like(tp), fn + frame.n_counted_gt, sim], axis=1).astype(np.float64)
    for i in range(len(gt_ignored)):
        if not above[i].any():  # nothing to match at any threshold
            fn += int(not gt_ignored[i])
            continue
        candidates = active & ~assigned & above[i]
        counted = candidates & ~det_ignored
        has_counted, has_candidate = counted.any(axis=1), candidates.any(axis=1)
        # highest overlap among counted candidates (first on ties), else the first ignored one
        j = np.where(has_counted, np.argmax(np.where(counted, frame.overlap[i], -np.inf), axis=1),
                     np.argmax(candidates, axis=1))
        assigned[rows[has_candidate], j[has_candidate]] = True
        if not gt_ignored[i]:
            tp += has_counted
            fn += ~has_candidate
            sim += np.where(has_counted, frame.similarity[i, j], 0.0)
    fp = np.count_nonzero(active & ~assigned & ~det_ignored, axis=1)
    return np.stack([tp, fp, fn, sim], axis=1).astype(np.float64)


def count_at_threshold(frame: FrameMatchInput, min_overlap: float, threshold: float) -> Counts:
    """(TP, FP, FN, similarity) of one frame counting only detections with score >= ``threshold``."""
    row = counts_at_thresholds(frame, min_overlap, np.array([threshold]))[0]
    return Counts(tp=int(row[TP]), fp=int(row[FP]), fn=int(row[FN]), similarity=float(row[SIM]))


def frame_threshold_events(frame: FrameMatchInput, min_overlap: float
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Score levels of one frame and the change of (TP, FP, FN) when the threshold drops to each.

    Returns ``levels`` (L,), the distinct detection scores in descending order, and ``deltas``
    (L, 4) with ``counts(levels[k]) - counts(levels[k - 1])`` (``counts(levels[-1])`` meaning "no
    detection": (0, 0, number of counted ground truth, 0)). For any threshold ``t`` the frame's
    counts are that base plus the sum of the deltas of the levels >= ``t``.
    """
    levels = np.unique(frame.scores)[::-1]
    if len(levels) == 0:
        return levels, np.zeros((0, N_COUNTS))
    counts = counts_at_thresholds(frame, min_overlap, levels)
    previous = np.concatenate([[[0.0, 0.0, frame.n_counted_gt, 0.0]], counts[:-1]])
    return levels, counts - previous
