"""Cameras: pixel rays in NumPy and the equivalent Mitsuba ``perspective`` sensor.

Pixel convention: ``(u, v) = (0, 0)`` is the centre of the top-left pixel (OpenCV); an image of
width W spans ``[-0.5, W - 0.5]``. Camera frames are OpenCV (x right, y down, z forward).

Mitsuba's camera frame is +x left, +y up, +z forward, so a sensor's ``to_world`` is
``cam_to_world @ diag(-1, -1, 1, 1)``. Mitsuba maps a film position ``p`` in ``[0, 1]^2`` (plus
``principal_point_offset``) through a centred pinhole with horizontal field of view ``fov``; pixel
``u`` is the film position ``(u + 0.5) / W``. The principal point ``(cx, cy)`` therefore lies on the
optical axis when ``principal_point_offset = 0.5 - ((cx, cy) + 0.5) / (W, H)``.

Mitsuba starts a ray on the near plane; the near clip is set to :data:`NEAR_CLIP` so that ray origins
are the camera centre to within ~1e-6 m.

The frame offset ``dt`` of a frame is carried as the ray time: ``shutter_open = shutter_close = dt``
(exposure 0), so a ray sampled at ``time = sensor.shutter_open()`` has ``ray.time == dt``.
"""

from __future__ import annotations

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant)
import mitsuba as mi

#: OpenCV camera -> Mitsuba camera axes (flip x and y).
CV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])

#: Near clip distance (m). Mitsuba starts a camera ray on the near plane; this keeps ray origins
#: within ~1e-6 m of the camera centre, so distances along a ray are distances from the camera
#: (directions are unaffected: they stay accurate to ~1e-7 for any near clip).
NEAR_CLIP = 1e-6

#: Relative tolerance on ``fx == fy``: Mitsuba's perspective camera has square pixels.
SQUARE_PIXEL_RTOL = 1e-6


def pixel_rays(K: np.ndarray, cam_to_world: np.ndarray, u: np.ndarray,
               v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays through pixel positions ``(u, v)``: origins (n, 3) and unit directions (n, 3) in world."""
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    v = np.atleast_1d(np.asarray(v, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    d_cam = pix @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T
    T = np.asarray(cam_to_world, dtype=np.float64)
    d = d_cam @ T[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.broadcast_to(T[:3, 3], d.shape).copy(), d


def to_mitsuba_transform(T: np.ndarray) -> mi.ScalarTransform4f:
    """A 4x4 NumPy matrix as a Mitsuba scalar transform."""
    return mi.ScalarTransform4f(np.asarray(T, dtype=np.float64).tolist())


def intrinsics_to_mitsuba(K: np.ndarray, image_size: tuple[int, int]) -> dict[str, float | str]:
    """``fov`` (degrees, along x) and principal point offsets reproducing pinhole intrinsics ``K``.

    Raises ValueError for non-square pixels (``fx != fy``) or skew, which Mitsuba cannot model.
    """
    K = np.asarray(K, dtype=np.float64)
    W, H = image_size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not np.isclose(fx, fy, rtol=SQUARE_PIXEL_RTOL, atol=0.0) or K[0, 1] != 0.0:
        raise ValueError(f"Mitsuba's perspective camera needs square pixels and no skew; K = {K.tolist()}")
    return {"fov": float(np.degrees(2.0 * np.arctan(W / (2.0 * fx)))), "fov_axis": "x",
            "principal_point_offset_x": float(0.5 - (cx + 0.5) / W),
            "principal_point_offset_y": float(0.5 - (cy + 0.5) / H)}


def perspective_sensor(K: np.ndarray, cam_to_world: np.ndarray, image_size: tuple[int, int],
                       frame_offset: int, sensor_id: str | None = None) -> dict:
    """``mi.load_dict`` description of a camera (see module doc for the conventions)."""
    W, H = int(image_size[0]), int(image_size[1])
    sensor = {
        "type": "perspective",
        **intrinsics_to_mitsuba(K, (W, H)),
        "near_clip": NEAR_CLIP,
        "shutter_open": float(frame_offset),
        "shutter_close": float(frame_offset),
        "to_world": to_mitsuba_transform(np.asarray(cam_to_world, dtype=np.float64) @ CV_TO_MITSUBA),
        "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}},
    }
    if sensor_id is not None:
        sensor["id"] = sensor_id
    return sensor
