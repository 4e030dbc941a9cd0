"""Pinhole cameras: the one implementation of projection and of a 3D box's 2D footprint."""

from __future__ import annotations

import dataclasses

import numpy as np

from .boxes import BOX_EDGES, Box3D
from .xp import NP

#: Stand-in for +-infinity in footprints (finite so gradients stay finite).
FAR_PX = 1e8

#: Points closer than this to the camera plane (metres) are clipped away before projection.
NEAR_PLANE = 0.1


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to points of shape (..., 3)."""
    pts = np.asarray(pts, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


def project(K: np.ndarray, pts_cam: np.ndarray) -> np.ndarray:
    """Project camera-frame points (..., 3) with intrinsics K (3x3); returns pixels (..., 2).

    Pixel (0, 0) is the centre of the top-left pixel (OpenCV convention), so an image of width W
    spans ``[-0.5, W - 0.5]``; see :func:`image_bounds`.
    """
    pts_cam = np.asarray(pts_cam, dtype=np.float64)
    uvw = pts_cam @ np.asarray(K, dtype=np.float64)[:3, :3].T
    return uvw[..., :2] / uvw[..., 2:3]


def image_bounds(image_size: tuple[int, int]) -> np.ndarray:
    """``(x1, y1, x2, y2)`` of the whole image in pixel-centre coordinates."""
    w, h = image_size
    return np.array([-0.5, -0.5, w - 0.5, h - 0.5])


def clip_edges_to_near(pts_cam: np.ndarray, edges: np.ndarray = BOX_EDGES,
                       near: float = NEAR_PLANE) -> np.ndarray:
    """Clip the segments ``pts_cam[edges]`` to ``z >= near``; returns the kept endpoints (M, 3)."""
    a, b = pts_cam[edges[:, 0]], pts_cam[edges[:, 1]]
    za, zb = a[:, 2], b[:, 2]
    keep_a, keep_b = za >= near, zb >= near
    out = [a[keep_a], b[keep_b]]
    crossing = keep_a ^ keep_b
    if np.any(crossing):
        t = (near - za[crossing]) / (zb[crossing] - za[crossing])
        out.append(a[crossing] + t[:, None] * (b[crossing] - a[crossing]))
    return np.concatenate(out, axis=0)


def footprint(corners, K, bounds, near: float = NEAR_PLANE, xp=NP):
    """2D footprint of a box from its 8 camera-frame corners; NumPy or Dr.Jit.

    ``corners`` is a sequence of 8 ``(x, y, z)`` triples of arrays (any shape, all alike),
    ``K`` a 3x3 intrinsic matrix (floats), ``bounds`` the image ``(x1, y1, x2, y2)``. The 12
    edges are clipped to ``z >= near``, the kept points projected and the enclosing rectangle
    clipped to ``bounds``. Returns ``(x1, y1, x2, y2, valid)``; ``valid`` is false where nothing
    of the box is in front of the camera or inside the image.
    """
    fx, fy, cx, cy = float(K[0][0]), float(K[1][1]), float(K[0][2]), float(K[1][2])
    s = float(K[0][1])
    x1 = y1 = FAR_PX
    x2 = y2 = -FAR_PX

    def add(p, keep, box):
        bx1, by1, bx2, by2 = box
        z = xp.maximum(p[2], near)
        u = (fx * p[0] + s * p[1]) / z + cx
        v = fy * p[1] / z + cy
        return (xp.where(keep, xp.minimum(bx1, u), bx1), xp.where(keep, xp.minimum(by1, v), by1),
                xp.where(keep, xp.maximum(bx2, u), bx2), xp.where(keep, xp.maximum(by2, v), by2))

    box = (x1, y1, x2, y2)
    kept = [c[2] >= near for c in corners]
    for c, keep in zip(corners, kept):
        box = add(c, keep, box)
    for i, j in BOX_EDGES:
        a, b = corners[i], corners[j]
        cross = kept[i] != kept[j]
        dz = b[2] - a[2]
        t = (near - a[2]) / xp.where(cross, dz, 1.0)
        q = tuple(a[k] + t * (b[k] - a[k]) for k in range(3))
        box = add((q[0], q[1], near + 0.0 * q[2]), cross, box)
    bx1, by1, bx2, by2 = bounds
    x1 = xp.minimum(xp.maximum(box[0], bx1), bx2)
    x2 = xp.minimum(xp.maximum(box[2], bx1), bx2)
    y1 = xp.minimum(xp.maximum(box[1], by1), by2)
    y2 = xp.minimum(xp.maximum(box[3], by1), by2)
    return x1, y1, x2, y2, (x2 > x1) & (y2 > y1)


def box_to_2d(box: Box3D, K: np.ndarray, world_to_cam: np.ndarray | None = None,
              image_size: tuple[int, int] | None = None, near: float = NEAR_PLANE,
              dt: float = 0.0) -> np.ndarray | None:
    """Axis-aligned 2D footprint ``(x1, y1, x2, y2)`` of a 3D box in an image.

    The box is moved by its velocity for frame offset ``dt``, brought into the camera frame by
    ``world_to_cam`` (identity if None), its 12 edges are clipped to ``z >= near``, the kept points
    projected, and the enclosing rectangle clipped to ``image_size = (width, height)``.
    Returns None when nothing of the box is in front of the camera or inside the image.
    """
    corners = box.at_offset(dt).corners()
    if world_to_cam is not None:
        corners = transform_points(world_to_cam, corners)
    bounds = image_bounds(image_size) if image_size is not None else (-FAR_PX, -FAR_PX, FAR_PX, FAR_PX)
    x1, y1, x2, y2, valid = footprint([tuple(c) for c in corners], K, bounds, near)
    if not valid:
        return None
    return np.array([x1, y1, x2, y2], dtype=np.float64)


#: How far the far end moves out (m): a tenth of a car's length.
LENGTH_PROBE_M = 0.5


def far_end_shift(box: Box3D, K: np.ndarray, image_size: tuple[int, int], probe: float = LENGTH_PROBE_M,
                  world_to_cam: np.ndarray | None = None, dt: float = 0.0) -> float | None:
    """How far (px, the largest of the four sides) ``box``'s 2D box (clipped to the image) moves
    when its end farther from the camera moves out by ``probe`` metres; None when the box is not
    in the image. ``world_to_cam`` and ``dt`` as in :func:`box_to_2d` (default: the box is in the
    camera frame, at its time)."""
    if probe <= 0:
        raise ValueError(f"far_end_shift: probe must be > 0 m, got {probe}")
    box = box.at_offset(dt)
    camera = np.zeros(3) if world_to_cam is None else np.linalg.inv(world_to_cam)[:3, 3]
    axis = box.rotation[:, 2]
    # |d + a l/2|^2 - |d - a l/2|^2 = 2 l (d . a), d the centre seen from the camera: the end at
    # +axis is the farther one when d . a > 0
    sign = 1.0 if float(np.dot(axis, np.asarray(box.centre) - camera)) >= 0.0 else -1.0
    size = np.array(box.size, dtype=np.float64)
    size[2] += probe
    longer = dataclasses.replace(box, centre=np.asarray(box.centre) + sign * 0.5 * probe * axis, size=size)
    before = box_to_2d(box, K, world_to_cam=world_to_cam, image_size=image_size)
    after = box_to_2d(longer, K, world_to_cam=world_to_cam, image_size=image_size)
    if before is None or after is None:
        return None
    return float(np.max(np.abs(after - before)))
