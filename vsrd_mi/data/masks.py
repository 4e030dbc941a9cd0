"""Instance masks: car extraction, tight 2D boxes, size filter and soft ray-sampling weights.

2D boxes use the pixel-centre convention of :mod:`vsrd_mi.geometry.camera`: pixel ``(x, y)`` is
the centre of the pixel, so a mask covering columns ``xmin..xmax`` has the tight box edges
``xmin - 0.5`` and ``xmax + 0.5`` and a width of ``xmax - xmin + 1`` pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from .labels import CAR_LABEL_ID, INSTANCE_FACTOR, OCCLUDING_LABEL_IDS

#: Smallest and largest instance-map value of a car (``26 * 1000 + 1`` .. ``26 * 1000 + 999``).
CAR_VALUE_MIN = CAR_LABEL_ID * INSTANCE_FACTOR + 1
CAR_VALUE_MAX = CAR_LABEL_ID * INSTANCE_FACTOR + INSTANCE_FACTOR - 1

#: Default length scale (pixels) of the soft sampling weight ``sigmoid(signed distance / scale)``.
SOFT_WEIGHT_SCALE_PX = 10.0
#: Order of the sides in :func:`open_sides`: those of a 2D box ``(x1, y1, x2, y2)``.
SIDES = ("left", "top", "right", "bottom")
#: A side of a mask is open when at least this share of its outermost pixels (those within
#: :data:`SIDE_BAND_PX` of the side) border an occluder or the image edge.
OPEN_SIDE_FRACTION = 0.25
#: Pixels from a side of the tight box that count as that side's outermost mask pixels, and how far
#: beyond each of them (in the side's direction) an occluder is looked for.
SIDE_BAND_PX = 2
SIDE_REACH_PX = 2
#: An instance whose lowest visible row is more than this many pixels above a car's stands behind
#: the car (:func:`lowest_rows`): about 1.5 m further at 20 m range on KITTI-360's rig (the bottom
#: row of a car 20 m away lies ~43 px below the horizon, 4 px less 2 m further away).
BEHIND_MARGIN_PX = 3


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


def occluder_map(instance_map: np.ndarray) -> np.ndarray:
    """Pixels that may hide a car: every car, and every class that stands in front of cars
    (:data:`~vsrd_mi.data.labels.OCCLUDING_LABEL_IDS`: people, vehicles, poles, signs, vegetation,
    bins, ...), whether a thing with an instance id (``label * 1000 + id``) or bare stuff."""
    labels = np.where(instance_map >= INSTANCE_FACTOR, instance_map // INSTANCE_FACTOR, instance_map)
    return np.isin(labels, OCCLUDING_LABEL_IDS)


def lowest_rows(instance_map: np.ndarray) -> np.ndarray:
    """``(2, H, W)``: per pixel, the lowest image row (largest y) of the thing instance it belongs
    to (values ``label * 1000 + id``) in the pixel's column (``[0]``) and over the whole instance
    (``[1]``); the image height ``H`` for stuff and unlabelled pixels, which are not ordered.

    Things stand on the ground, which a camera above it sees rising towards the horizon: of two
    things that meet in the image, the one whose bottom is higher stands further away, unless its
    bottom is hidden by something nearer. :func:`open_sides` takes a thing for one standing behind
    a car only where both rows say so: the column's, since a car in an angled row reaches nearer
    the camera at its front end than its neighbour's nearest corner does, though its own nearest
    corner lies further; and the whole instance's, since a sign's board hangs beside its pole.
    """
    instance_map = np.asarray(instance_map)
    H, W = instance_map.shape
    out = np.full((2, H, W), H, dtype=np.int32)
    ys, xs = np.nonzero(instance_map >= INSTANCE_FACTOR)
    if ys.size == 0:
        return out
    _, index = np.unique(instance_map[ys, xs], return_inverse=True)
    column = np.full((int(index.max()) + 1, W), -1, dtype=np.int32)
    np.maximum.at(column, (index, xs), ys.astype(np.int32))
    out[0, ys, xs] = column[index, xs]
    out[1, ys, xs] = column.max(axis=1)[index]
    return out


def open_sides(mask: np.ndarray, occluders: np.ndarray, lowest: np.ndarray | None = None) -> np.ndarray:
    """Which sides ``(left, top, right, bottom)`` of a mask's tight box may not be the object's.

    The mask's outermost pixels on a side (within :data:`SIDE_BAND_PX` of it) are looked past, up to
    :data:`SIDE_REACH_PX` pixels outwards: where the image ends or an occluder (``occluders``, e.g.
    :func:`occluder_map`, the mask's own pixels aside) lies there, the object may go on behind it.
    Past the left and right sides the look spans 45 degrees either side of outwards: a car's end
    is often a point of its silhouette (a sloping rear window, a rounded bumper) that an
    occluder's edge meets at a slant, below or above the point rather than beside it, and a car
    in front hides the rest of the end there all the same. The top and bottom are runs along the
    roof and the ground, which the straight look covers, and a slanted look past them would reach
    the cars beside the roof's ends.
    A side is open when at least :data:`OPEN_SIDE_FRACTION` of its outermost pixels are. A mask
    that reaches the image's left or right edge has its top and bottom open as well: the part of
    the car beyond the edge may hold its roof or its nearest wheel (a near car cut by the edge
    often shows only a bumper and a wing), which reach higher and lower than the part inside. A
    side cut by an occluder does not open the top and bottom: most cars in rows are cut by their
    neighbours, and bounded only from inside their heights grow (docs/accuracy.md). With
    ``lowest`` (:func:`lowest_rows` of the instance map ``mask`` is one instance of, which holds the
    mask's own lowest rows at its pixels) an occluder pixel stands behind the
    object and hides nothing where its thing's lowest row in its column lies more than
    :data:`BEHIND_MARGIN_PX` above the mask's lowest row in the column of the side pixel it was
    looked for from, and its thing's lowest row overall likewise above the mask's: the row of cars
    further down a street borders a nearer car's roof in the image.
    Without it, or for stuff (vegetation, bare poles), the test is conservative: an occluder behind
    the car opens a side too, which only drops a constraint. Returns a (4,) bool array (all False
    for an empty mask).
    """
    mask = np.asarray(mask, dtype=bool)
    out = np.zeros(4, dtype=bool)
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return out
    H, W = mask.shape
    blocked = np.asarray(occluders, dtype=bool) & ~mask
    if lowest is not None:
        lowest = np.asarray(lowest)
    bounds = (xs.min(), ys.min(), xs.max(), ys.max())
    # (coordinate array, extreme, outward step along x, along y)
    for k, (coord, extreme, dx, dy) in enumerate(((xs, bounds[0], -1, 0), (ys, bounds[1], 0, -1),
                                                  (xs, bounds[2], 1, 0), (ys, bounds[3], 0, 1))):
        edge = np.abs(coord - extreme) < SIDE_BAND_PX
        ex, ey = xs[edge], ys[edge]
        hit = np.zeros(len(ex), dtype=bool)
        own = None if lowest is None else lowest[:, ey, ex]   # the mask's column and overall lowest rows
        for step in range(1, SIDE_REACH_PX + 1):
            # left and right: within 45 degrees of outwards (see the docstring)
            for lateral in range(-step, step + 1) if dx else (0,):
                qx, qy = ex + dx * step, ey + dy * step + lateral
                inside = (qx >= 0) & (qx < W) & (qy >= 0) & (qy < H)
                if lateral == 0:
                    hit |= ~inside                        # past the image edge
                here = blocked[qy[inside], qx[inside]]
                if lowest is not None:  # not an occluder where it stands clearly behind the object
                    here &= ~np.all(lowest[:, qy[inside], qx[inside]] < own[:, inside] - BEHIND_MARGIN_PX, axis=0)
                hit[inside] |= here
        out[k] = hit.mean() >= OPEN_SIDE_FRACTION
    if bounds[0] == 0 or bounds[2] == W - 1:
        out[[1, 3]] = True        # cut by the image's side: its roof or nearest wheel may lie beyond
    return out


def _distance_to_zero(m: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance from each non-zero pixel centre to the nearest zero pixel centre."""
    return cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def max_signed_distance(masks: np.ndarray) -> np.ndarray:
    """Largest signed distance (px) over instances from each pixel to an instance mask boundary.

    The signed distance of one mask is the exact Euclidean distance to the nearest pixel centre on
    the other side minus half a pixel (positive inside), so a pixel next to the boundary is at
    +-0.5; this is exact along rows and columns and overshoots the distance to a mask corner by at
    most ``(sqrt(2) - 1) / 2 ~ 0.21`` px. The image border is not a boundary (masks truncated by
    the image continue beyond it).

    Outside every mask the maximum is minus the distance to the union of the masks (one distance
    transform of the whole image); inside mask ``n`` it is that mask's own inside distance,
    computed in its bounding box padded by one pixel (the nearest outside pixel always lies within
    that padded box). Returns float32 (H, W); -inf everywhere when all masks are empty, +inf where
    a mask covers the whole image.
    """
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3:
        raise ValueError(f"masks must be (N, H, W), got shape {masks.shape}")
    H, W = masks.shape[1:]
    union = masks.any(axis=0)
    if not union.any():
        return np.full((H, W), -np.inf, dtype=np.float32)
    if union.all():
        out = np.full((H, W), -np.inf, dtype=np.float32)
    else:
        out = -(_distance_to_zero(~union) - 0.5)
        out[union] = -np.inf
    for m in masks:
        box = tight_box(m)
        if box is None:
            continue
        x0, y0 = max(int(box[0] + 0.5) - 1, 0), max(int(box[1] + 0.5) - 1, 0)
        x1, y1 = min(int(box[2] - 0.5) + 2, W), min(int(box[3] - 0.5) + 2, H)
        crop = m[y0:y1, x0:x1]
        inside = np.full(crop.shape, np.inf, dtype=np.float32) if crop.all() else _distance_to_zero(crop) - 0.5
        view = out[y0:y1, x0:x1]
        view[crop] = np.maximum(view[crop], inside[crop])
    return out.astype(np.float32)


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance (px) of one mask, positive inside (see :func:`max_signed_distance`)."""
    return max_signed_distance(np.asarray(mask, dtype=bool)[None])


def soft_weight(masks: np.ndarray, scale: float = SOFT_WEIGHT_SCALE_PX) -> np.ndarray:
    """Ray-sampling weight of one frame: ``sigmoid(signed distance / scale)`` (docs/method.md §3).

    ``masks`` is (N, H, W) bool for the N target instances. Instances are combined by the maximum
    of their per-instance weights, which (sigmoid being monotone) is the sigmoid of the largest
    signed distance (:func:`max_signed_distance`): a pixel is weighted by its closest / deepest
    instance. A frame where no instance is visible gets weight 0 everywhere. Returns float32 (H, W).
    """
    best = max_signed_distance(masks)
    with np.errstate(over="ignore"):
        return (1.0 / (1.0 + np.exp(-best / scale))).astype(np.float32)
