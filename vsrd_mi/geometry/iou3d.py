"""Exact bird's-eye-view (BEV) and 3D IoU of gravity-aligned boxes (docs/method.md §9).

A :class:`~vsrd_mi.geometry.boxes.Box3D` is a rectangle in the ground (x-z) plane, rotated by its
yaw, extruded along the vertical y axis. Therefore

* BEV IoU = area(A_xz ∩ B_xz) / (area(A_xz) + area(B_xz) - area(A_xz ∩ B_xz)), with the
  intersection of the two rotated rectangles computed exactly (polygon overlay by shapely/GEOS,
  double precision, no float32 corner tests, no epsilon in any denominator);
* 3D IoU = area(A_xz ∩ B_xz) * overlap(A_y, B_y) / (vol(A) + vol(B) - intersection volume).

Rectangle areas and volumes are the analytic products of the box sizes, so two identical boxes give
an IoU of 1 to rounding (~1e-15). The footprint corners come from :meth:`Box3D.corners`, the one
implementation of box corners.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import shapely

from .boxes import Box3D

#: Indices into :meth:`Box3D.corners` of the four top-face corners, in ring order (consecutive
#: corners share an edge), which project onto the box's footprint in the x-z plane.
FOOTPRINT_CORNERS = np.array([0, 1, 2, 3])

#: Columns of a camera-frame point holding the ground-plane coordinates (x, z).
GROUND_AXES = np.array([0, 2])

#: Column of a camera-frame point holding the vertical coordinate (y, pointing down).
VERTICAL_AXIS = 1


def bev_footprint(box: Box3D) -> np.ndarray:
    """The box's footprint in the ground plane: its 4 corners ``(x, z)`` in ring order, shape (4, 2)."""
    return box.corners()[FOOTPRINT_CORNERS][:, GROUND_AXES]


def vertical_extent(box: Box3D) -> tuple[float, float]:
    """``(y_min, y_max)`` of the box along the vertical (y-down) axis."""
    half = 0.5 * box.size[VERTICAL_AXIS]
    y = box.centre[VERTICAL_AXIS]
    return float(y - half), float(y + half)


def _footprint_areas(boxes: Sequence[Box3D]) -> np.ndarray:
    """Analytic footprint areas ``w * l`` of ``boxes``, shape (N,)."""
    return np.array([b.size[0] * b.size[2] for b in boxes], dtype=np.float64).reshape(-1)


def _polygons(boxes: Sequence[Box3D]) -> np.ndarray:
    """Shapely polygons of the footprints of ``boxes``, shape (N,)."""
    if len(boxes) == 0:
        return np.empty(0, dtype=object)
    return shapely.polygons(np.stack([bev_footprint(b) for b in boxes]))


def bev_intersection_matrix(a: Sequence[Box3D], b: Sequence[Box3D]) -> np.ndarray:
    """Pairwise footprint intersection areas (m^2) of boxes ``a`` (N) and ``b`` (M) -> (N, M)."""
    pa, pb = _polygons(a), _polygons(b)
    if len(pa) == 0 or len(pb) == 0:
        return np.zeros((len(pa), len(pb)))
    inter = shapely.area(shapely.intersection(pa[:, None], pb[None, :]))
    return np.asarray(inter, dtype=np.float64).reshape(len(pa), len(pb))


def vertical_overlap_matrix(a: Sequence[Box3D], b: Sequence[Box3D]) -> np.ndarray:
    """Pairwise lengths (m) of the overlap of the vertical extents of ``a`` and ``b`` -> (N, M)."""
    ea = np.array([vertical_extent(x) for x in a], dtype=np.float64).reshape(-1, 2)
    eb = np.array([vertical_extent(x) for x in b], dtype=np.float64).reshape(-1, 2)
    lo = np.maximum(ea[:, None, 0], eb[None, :, 0])
    hi = np.minimum(ea[:, None, 1], eb[None, :, 1])
    return np.maximum(hi - lo, 0.0)


def iou_matrices(a: Sequence[Box3D], b: Sequence[Box3D]) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise ``(BEV IoU, 3D IoU)`` of boxes ``a`` (N) and ``b`` (M), each of shape (N, M).

    Both share one polygon intersection per pair. Every box has positive size (enforced by
    :class:`Box3D`), so no denominator can be zero and none is padded.
    """
    inter_area = bev_intersection_matrix(a, b)
    area_a, area_b = _footprint_areas(a), _footprint_areas(b)
    bev = inter_area / (area_a[:, None] + area_b[None, :] - inter_area)
    height_a = np.array([x.size[VERTICAL_AXIS] for x in a], dtype=np.float64).reshape(-1)
    height_b = np.array([x.size[VERTICAL_AXIS] for x in b], dtype=np.float64).reshape(-1)
    inter_vol = inter_area * vertical_overlap_matrix(a, b)
    vol_a, vol_b = area_a * height_a, area_b * height_b
    iou3d_ = inter_vol / (vol_a[:, None] + vol_b[None, :] - inter_vol)
    return bev, iou3d_


def bev_iou_matrix(a: Sequence[Box3D], b: Sequence[Box3D]) -> np.ndarray:
    """Pairwise BEV IoU of boxes ``a`` (N) and ``b`` (M) -> (N, M)."""
    return iou_matrices(a, b)[0]


def iou3d_matrix(a: Sequence[Box3D], b: Sequence[Box3D]) -> np.ndarray:
    """Pairwise 3D IoU of boxes ``a`` (N) and ``b`` (M) -> (N, M)."""
    return iou_matrices(a, b)[1]


def bev_iou(a: Box3D, b: Box3D) -> float:
    """BEV IoU of two boxes."""
    return float(bev_iou_matrix([a], [b])[0, 0])


def iou3d(a: Box3D, b: Box3D) -> float:
    """3D IoU of two boxes."""
    return float(iou3d_matrix([a], [b])[0, 0])
