"""Instance masks: car extraction, tight 2D boxes, size filter and soft ray-sampling weights.

2D boxes use the pixel-centre convention of :mod:`vsrd_mi.geometry.camera`: pixel ``(x, y)`` is
the centre of the pixel, so a mask covering columns ``xmin..xmax`` has the tight box edges
``xmin - 0.5`` and ``xmax + 0.5`` and a width of ``xmax - xmin + 1`` pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from .kitti360 import CAR_LABEL_ID, INSTANCE_FACTOR

#: Smallest and largest instance-map value of a car (``26 * 1000 + 1`` .. ``26 * 1000 + 999``).
CAR_VALUE_MIN = CAR_LABEL_ID * INSTANCE_FACTOR + 1
CAR_VALUE_MAX = CAR_LABEL_ID * INSTANCE_FACTOR + INSTANCE_FACTOR - 1

#: Default length scale (pixels) of the soft sampling weight ``sigmoid(signed distance / scale)``.
SOFT_WEIGHT_SCALE_PX = 10.0


def car_values(instance_map: np.ndarray) -> np.ndarray:
    """Sorted car instance values (26001..26999) present in an instance map."""
    values = np.unique(instance_map)
    return values[(values >= CAR_VALUE_MIN) & (values <= CAR_VALUE_MAX)].astype(np.int64)


def car_masks(instance_map: np.ndarray) -> dict[int, np.ndarray]:
    """Boolean mask of every car in ``instance_map``, keyed by its pixel value."""
    return {int(v): instance_map == v for v in car_values(instance_map)}


def tight_box(mask: np.ndarray) -> np.ndarray | None:
    """Tight 2D box ``(xmin - 0.5, ymin - 0.5, xmax + 0.5, ymax + 0.5)`` of a mask; None if empty."""
    cols = np.flatnonzero(mask.any(axis=0))
    if cols.size == 0:
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return np.array([cols[0] - 0.5, rows[0] - 0.5, cols[-1] + 0.5, rows[-1] + 0.5])


def passes_size_filter(mask: np.ndarray, min_area: int, min_box_side: float) -> bool:
    """Whether a mask has at least ``min_area`` pixels and a tight box of min side >= ``min_box_side`` px."""
    if int(mask.sum()) < min_area:
        return False
    box = tight_box(mask)
    return box is not None and min(box[2] - box[0], box[3] - box[1]) >= min_box_side


def valid_car_ids(instance_map: np.ndarray, min_area: int, min_box_side: float) -> frozenset[int]:
    """Car values whose masks pass :func:`passes_size_filter`.

    Works on the car pixels only (one pass to find them, then per instance on that subset).
    """
    car = (instance_map >= CAR_VALUE_MIN) & (instance_map <= CAR_VALUE_MAX)
    ys, xs = np.nonzero(car)
    vals = instance_map[ys, xs]
    out = set()
    for v in np.unique(vals):
        sel = vals == v
        if int(sel.sum()) < min_area:
            continue
        w = xs[sel].max() - xs[sel].min() + 1
        h = ys[sel].max() - ys[sel].min() + 1
        if min(w, h) >= min_box_side:
            out.add(int(v))
    return frozenset(out)


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance in pixels from each pixel centre to the mask boundary, positive inside.

    Computed as the exact Euclidean distance to the nearest pixel centre on the other side minus
    half a pixel, so a pixel next to the boundary is at +-0.5; this is exact along rows and columns
    and overshoots the distance to a mask corner by at most ``(sqrt(2) - 1) / 2 ~ 0.21`` px, far below
    the 10 px scale of the weights. An empty mask is -inf everywhere, a full one +inf.
    """
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return np.full(mask.shape, -np.inf, dtype=np.float32)
    if mask.all():
        return np.full(mask.shape, np.inf, dtype=np.float32)
    m = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(mask, inside - 0.5, -(outside - 0.5)).astype(np.float32)


def soft_weight(masks: np.ndarray, scale: float = SOFT_WEIGHT_SCALE_PX) -> np.ndarray:
    """Ray-sampling weight of one frame: ``sigmoid(signed distance / scale)`` (REFERENCE §3).

    ``masks`` is (N, H, W) bool for the N target instances. Instances are combined by the maximum
    of their per-instance weights, which (sigmoid being monotone) is the sigmoid of the largest
    signed distance: a pixel is weighted by its closest / deepest instance. A frame where no
    instance is visible gets weight 0 everywhere. Returns float32 (H, W).
    """
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3:
        raise ValueError(f"masks must be (N, H, W), got shape {masks.shape}")
    best = np.full(masks.shape[1:], -np.inf, dtype=np.float32)
    for m in masks:
        best = np.maximum(best, signed_distance(m))
    with np.errstate(over="ignore"):
        return (1.0 / (1.0 + np.exp(-best / scale))).astype(np.float32)
