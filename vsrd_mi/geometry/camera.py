"""Pinhole cameras: the one implementation of projection and of a 3D box's 2D footprint."""

from __future__ import annotations

import numpy as np

from .boxes import BOX_EDGES, Box3D

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
    pts = clip_edges_to_near(corners, near=near)
    if len(pts) == 0:
        return None
    uv = project(K, pts)
    x1, y1 = uv.min(axis=0)
    x2, y2 = uv.max(axis=0)
    if image_size is not None:
        bx1, by1, bx2, by2 = image_bounds(image_size)
        x1, x2 = np.clip([x1, x2], bx1, bx2)
        y1, y2 = np.clip([y1, y2], by1, by2)
    if x2 <= x1 or y2 <= y1:
        return None
    return np.array([x1, y1, x2, y2])
