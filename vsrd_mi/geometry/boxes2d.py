"""Axis-aligned 2D boxes: the one implementation of IoU and DIoU.

The formulas are written against an array namespace ``xp`` providing ``minimum`` and ``maximum``
so that the same code runs on NumPy arrays (data, confidence, evaluation) and on Dr.Jit arrays
(the differentiable projection loss): pass ``xp=numpy`` or ``xp=drjit``. A box is a sequence of
four components ``(x1, y1, x2, y2)``, each an array of the same shape.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

#: Added to denominators; small enough not to bias IoU (< 1e-9 for boxes of >= 1 px^2).
EPS = 1e-9


def area(b: Sequence[Any], xp: Any = np) -> Any:
    return xp.maximum(b[2] - b[0], 0.0) * xp.maximum(b[3] - b[1], 0.0)


def intersection(a: Sequence[Any], b: Sequence[Any], xp: Any = np) -> Any:
    w = xp.maximum(xp.minimum(a[2], b[2]) - xp.maximum(a[0], b[0]), 0.0)
    h = xp.maximum(xp.minimum(a[3], b[3]) - xp.maximum(a[1], b[1]), 0.0)
    return w * h


def iou(a: Sequence[Any], b: Sequence[Any], xp: Any = np) -> Any:
    """Intersection over union of boxes ``a`` and ``b`` (element-wise)."""
    inter = intersection(a, b, xp)
    return inter / (area(a, xp) + area(b, xp) - inter + EPS)


def diou(a: Sequence[Any], b: Sequence[Any], xp: Any = np) -> Any:
    """Distance-IoU (Zheng et al. 2020): ``IoU - |c_a - c_b|^2 / diag(enclosing box)^2``."""
    cx = 0.5 * (a[0] + a[2] - b[0] - b[2])
    cy = 0.5 * (a[1] + a[3] - b[1] - b[3])
    ex = xp.maximum(a[2], b[2]) - xp.minimum(a[0], b[0])
    ey = xp.maximum(a[3], b[3]) - xp.minimum(a[1], b[1])
    return iou(a, b, xp) - (cx * cx + cy * cy) / (ex * ex + ey * ey + EPS)


def _split(boxes: np.ndarray) -> list[np.ndarray]:
    boxes = np.asarray(boxes, dtype=np.float64)
    return [boxes[..., i] for i in range(4)]


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of NumPy boxes ``a`` (N, 4) and ``b`` (M, 4) -> (N, M)."""
    return iou(_split(np.asarray(a)[:, None, :]), _split(np.asarray(b)[None, :, :]))


def diou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise DIoU of NumPy boxes ``a`` (N, 4) and ``b`` (M, 4) -> (N, M)."""
    return diou(_split(np.asarray(a)[:, None, :]), _split(np.asarray(b)[None, :, :]))
