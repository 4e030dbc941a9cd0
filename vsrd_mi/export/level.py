"""Level cameras: exact KITTI labels for a pitched and rolled camera (``export-dataset --level``).

A KITTI label holds a box's yaw only: its vertical axis is the camera's y axis. KITTI-360's left
camera looks down by about 6 degrees and rolls by about 1, so a car standing on the road is tilted
in that camera's frame and no label describes it: the label written for it keeps the exact centre
and size, and the heading's direction in the camera's x-z plane, but stands the box up along the
camera's y axis, so its projection misses the car's 2D box.

The level camera of a frame has the same centre and intrinsics ``K`` and axes level with the road:

* ``y`` is the world's down direction: KITTI-360's world is z-up, so "level" is read off the
  frame's pose (``cam0_to_world``), not fitted to the image;
* ``z`` is the camera's optical axis projected onto the horizontal plane (the yaw is kept);
* ``x = y x z``.

:func:`level_rotation` gives the rotation ``R`` (rectified camera -> level camera coordinates,
rows = the level axes). The image turns by the homography ``K R K^-1`` (:func:`level_image`):
same size, the band the original image does not cover filled black. A label box turns by
:func:`level_box`: its centre rotates with ``R`` and its heading is the horizontal direction whose
projection on the camera's x-z plane has the label's yaw (exact for every box whose true vertical
is the world's, which holds for KITTI-360's ground truth and, within the optimisation frame's roll,
for our boxes). The 2D box of a level label is the level 3D box projected with ``K`` and clipped
to the image (:func:`level_labels`), so a level label's 3D box always lands on its 2D box.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterable, Sequence

import cv2
import numpy as np

from ..data.kitti_labels import KittiLabel, box_from_label, label_from_box
from ..data.observations import WORLD_UP
from ..geometry.boxes import Box3D, yaw_from_direction
from ..geometry.camera import box_to_2d

#: A camera whose down direction is further than this from its own y axis (cosine) is not a road
#: camera looking roughly level; "level" is then not defined by turning it (60 degrees).
MIN_DOWN_COSINE = 0.5


def level_rotation(cam_to_world: np.ndarray, world_up: np.ndarray = WORLD_UP) -> np.ndarray:
    """3x3 rotation from a camera's coordinates to those of its level camera (module docstring).

    ``cam_to_world`` is the 4x4 (or 3x3 rotation) camera -> world of a frame whose world has
    up vector ``world_up``. Raises ValueError for a camera looking too far up or down.
    """
    R_cw = np.asarray(cam_to_world, dtype=np.float64)[:3, :3]
    down = -R_cw.T @ (np.asarray(world_up, dtype=np.float64) / np.linalg.norm(world_up))
    down /= np.linalg.norm(down)
    if down[1] < MIN_DOWN_COSINE:
        raise ValueError(f"the camera's y axis is {np.degrees(np.arccos(np.clip(down[1], -1, 1))):.0f} deg "
                         f"from the world's down direction: not a level-looking road camera")
    forward = np.array([0.0, 0.0, 1.0]) - down[2] * down
    forward /= np.linalg.norm(forward)
    return np.stack([np.cross(down, forward), down, forward])


def level_homography(K: np.ndarray, R: np.ndarray) -> np.ndarray:
    """3x3 homography ``K R K^-1`` taking a pixel of the camera to the same ray's pixel in the
    level camera (pixel-centre coordinates, as :func:`vsrd_mi.geometry.camera.project`)."""
    K = np.asarray(K, dtype=np.float64)[:3, :3]
    return K @ np.asarray(R, dtype=np.float64) @ np.linalg.inv(K)


def level_image(image: np.ndarray, K: np.ndarray, R: np.ndarray, nearest: bool = False) -> np.ndarray:
    """The image the level camera sees: ``image`` warped by :func:`level_homography`, the same
    size, pixels the original does not cover black (0). Bilinear, or nearest-neighbour for label
    images such as instance maps (``nearest``)."""
    h, w = image.shape[:2]
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.warpPerspective(image, level_homography(K, R), (w, h), flags=flags,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def level_box(box_cam: Box3D, R: np.ndarray) -> Box3D:
    """The box of a camera-frame label (:func:`~vsrd_mi.data.kitti_labels.box_from_label`)
    in the level camera of rotation ``R``.

    The label's box stands along the camera's y axis; the true box stands along the level
    vertical ``R[1]`` (in camera coordinates). Its heading ``h`` is horizontal (``h . R[1] = 0``)
    and its projection on the camera's x-z plane points along the label's yaw, so ``h`` lies in
    the plane of ``u = (sin yaw, 0, cos yaw)`` and ``e_y``: ``h = u - (u . v / v_y) e_y``.
    """
    R = np.asarray(R, dtype=np.float64)
    vertical = R[1]
    u = np.array([np.sin(box_cam.yaw), 0.0, np.cos(box_cam.yaw)])
    heading = u - (u @ vertical / vertical[1]) * np.array([0.0, 1.0, 0.0])
    return replace(box_cam, centre=R @ box_cam.centre, yaw=yaw_from_direction(R @ heading),
                   velocity=R @ box_cam.velocity)


def level_label(label: KittiLabel, R: np.ndarray, K: np.ndarray, image_size: tuple[int, int]) -> KittiLabel | None:
    """The label in the level camera: :func:`level_box` of its box, the 2D box that box's
    projection clipped to the image; None when nothing of it is in the level image."""
    box = level_box(box_from_label(label), R)
    box2d = box_to_2d(box, K, image_size=image_size)
    if box2d is None:
        return None
    return label_from_box(box, box2d, score=label.score, type=label.type, truncated=label.truncated,
                          occluded=label.occluded)


def level_labels(labels: Iterable[KittiLabel], R: np.ndarray, K: np.ndarray,
                 image_size: tuple[int, int]) -> tuple[list[KittiLabel], int]:
    """:func:`level_label` of every label; returns the level labels and how many fell outside."""
    out: list[KittiLabel] = []
    dropped = 0
    for label in labels:
        level = level_label(label, R, K, image_size)
        if level is None:
            dropped += 1
        else:
            out.append(level)
    return out, dropped


def pitch_roll_deg(R: np.ndarray) -> tuple[float, float]:
    """Pitch and roll (degrees) of the camera whose level rotation is ``R``: pitch is positive
    when the optical axis points below the horizon, roll when the image's x axis (right) does."""
    down = np.asarray(R, dtype=np.float64)[1]
    return float(np.degrees(np.arctan2(down[2], down[1]))), float(np.degrees(np.arctan2(down[0], down[1])))


def apply_homography(H: np.ndarray, pts: Sequence[Sequence[float]]) -> np.ndarray:
    """Pixel points (N, 2) mapped by the 3x3 homography ``H``."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    p = np.hstack([pts, np.ones((len(pts), 1))]) @ np.asarray(H, dtype=np.float64).T
    return p[:, :2] / p[:, 2:3]
