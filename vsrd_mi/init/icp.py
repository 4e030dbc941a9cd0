"""Translation-only ICP between two point clouds (velocity initialisation, VSRD++ eq. 11).

Only a translation is estimated: a car does not turn noticeably between frames a few tenths of a
second apart, and a rotation would absorb the viewpoint-dependent change of the visible surface.
The translation starts at the difference of the centroids (robust to large motion), and each
iteration moves the source by the mean offset to its nearest target points, keeping only the
best ``trim_fraction`` of the correspondences (trimmed ICP: partial overlap).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .pointcloud import subsample


@dataclass(frozen=True)
class ICPResult:
    """Outcome of :func:`icp_translation`."""

    #: Translation (3,) such that ``source + translation`` matches ``target``.
    translation: np.ndarray
    #: RMS distance of the kept correspondences at the end (m).
    rms: float
    #: Iterations run.
    iterations: int
    #: Whether the update fell below the tolerance before the iteration limit.
    converged: bool


def icp_translation(source: np.ndarray, target: np.ndarray, max_iterations: int = 50,
                    tolerance: float = 1e-4, trim_fraction: float = 0.8,
                    target_tree: cKDTree | None = None,
                    initial: np.ndarray | None = None) -> ICPResult:
    """Translation aligning ``source`` (N, 3) onto ``target`` (M, 3).

    Args:
        max_iterations: iteration limit.
        tolerance: stop when the translation update is shorter than this (m).
        trim_fraction: fraction (0, 1] of the closest correspondences used per update.
        target_tree: a prebuilt ``cKDTree(target)`` (saves rebuilding it for many pairs).
        initial: starting translation (default: centroid difference).
    """
    if len(source) == 0 or len(target) == 0:
        raise ValueError("ICP needs two non-empty clouds")
    if not 0 < trim_fraction <= 1:
        raise ValueError(f"trim_fraction must be in (0, 1], got {trim_fraction}")
    tree = target_tree if target_tree is not None else cKDTree(target)
    t = (target.mean(axis=0) - source.mean(axis=0)) if initial is None else np.asarray(initial, float)
    n_keep = max(1, int(round(trim_fraction * len(source))))
    rms, converged, it = np.inf, False, 0
    for it in range(1, max_iterations + 1):
        moved = source + t
        dist, idx = tree.query(moved)
        keep = np.argpartition(dist, n_keep - 1)[:n_keep] if n_keep < len(dist) else slice(None)
        step = (target[idx[keep]] - moved[keep]).mean(axis=0)
        t = t + step
        rms = float(np.sqrt(np.mean(dist[keep] ** 2)))
        if np.linalg.norm(step) < tolerance:
            converged = True
            break
    return ICPResult(translation=t, rms=rms, iterations=it, converged=converged)


def register_translation(a: np.ndarray, b: np.ndarray, tree_a: cKDTree | None = None,
                         tree_b: cKDTree | None = None, max_source_points: int | None = None,
                         rms_tolerance_abs: float = 0.02, rms_tolerance_rel: float = 0.1,
                         **kwargs) -> ICPResult:
    """Translation from cloud ``a`` to cloud ``b`` of the same (rigid) object, robust to partial views.

    Four trimmed ICP runs: both directions (``a`` onto ``b``, and ``b`` onto ``a`` negated), each
    started from zero motion and from the centroid difference. A partially occluded or partially
    visible object makes the problem degenerate (a flat face slides along itself at no cost, and
    the centroid moves with the occlusion boundary), so among the runs whose trimmed RMS is
    within ``rms_tolerance_abs + rms_tolerance_rel * best`` of the best one the smallest
    translation is taken (Occam's razor: no more motion than the data demand). A large true
    motion leaves the zero-motion runs at a clearly worse RMS, so it is kept.

    ``max_source_points`` subsamples the moving cloud of each run (the fixed one keeps all
    points); other keyword arguments go to :func:`icp_translation`. The result's ``iterations``
    is the sum over the runs and ``converged`` that of the chosen run.
    """
    tree_a = tree_a if tree_a is not None else cKDTree(a)
    tree_b = tree_b if tree_b is not None else cKDTree(b)
    src_a = a if max_source_points is None else subsample(a, max_source_points)
    src_b = b if max_source_points is None else subsample(b, max_source_points)
    runs = []
    for sign, src, dst, tree in ((1.0, src_a, b, tree_b), (-1.0, src_b, a, tree_a)):
        for initial in (np.zeros(3), None):
            r = icp_translation(src, dst, target_tree=tree, initial=initial, **kwargs)
            runs.append(ICPResult(sign * r.translation, r.rms, r.iterations, r.converged))
    best = min(r.rms for r in runs)
    ok = [r for r in runs if r.rms <= best * (1.0 + rms_tolerance_rel) + rms_tolerance_abs]
    chosen = min(ok, key=lambda r: float(np.linalg.norm(r.translation)))
    return ICPResult(chosen.translation, chosen.rms, sum(r.iterations for r in runs),
                     chosen.converged)
