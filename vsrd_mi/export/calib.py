"""KITTI object-detection calibration files (``training/calib/%06d.txt``) for exported frames.

A KITTI calib file holds seven lines ``KEY: v1 v2 ...``, in this order (loaders such as MonoDETR's
read them by line number), every value written as ``%.12e`` and separated by single spaces::

    P0, P1, P2, P3      3x4 projection matrices (12 values, row-major) of KITTI's four cameras,
                        from the rectified reference frame of the labels
    R0_rect             3x3 rectifying rotation (9 values)
    Tr_velo_to_cam      3x4 Velodyne -> reference camera (12 values)
    Tr_imu_to_velo      3x4 IMU -> Velodyne (12 values)

What the exported set writes (``docs/export.md``):

* ``P2`` (the camera of the labels and of ``image_2``) and ``P0`` are KITTI-360's left rectified
  camera ``P_rect_00``; ``P3`` and ``P1`` its right camera ``P_rect_01``. With ``--level`` each
  is the virtual camera of the same intrinsics and centre turned level (:mod:`.level`), and the
  labels are in that frame;
* ``R0_rect`` is the identity: labels are already in the rectified (or level) frame;
* KITTI-360's rectified frames come without a Velodyne scan here, so ``Tr_velo_to_cam`` describes
  a virtual sensor at the camera centre with KITTI's Velodyne axes (x forward, y left, z up):
  :data:`VELO_TO_CAM`, a fixed axis permutation. A loader that converts camera boxes to "LiDAR"
  boxes gets boxes in that frame (upright with ``--level``);
* ``Tr_imu_to_velo`` maps KITTI-360's IMU / GPS pose frame to that virtual sensor, from
  ``calib_cam_to_pose.txt`` (identity when the dataset lacks the file).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..data.kitti360 import Calibration
from ..errors import DataError

#: Keys of a KITTI calib file, in file order, with their matrix shapes.
CALIB_KEYS: dict[str, tuple[int, int]] = {
    "P0": (3, 4), "P1": (3, 4), "P2": (3, 4), "P3": (3, 4),
    "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4), "Tr_imu_to_velo": (3, 4),
}

#: Rotation from KITTI's Velodyne axes (x forward, y left, z up) to the camera's (x right, y down,
#: z forward): the virtual sensor of ``Tr_velo_to_cam``.
VELO_TO_CAM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

#: printf format of every calib value (KITTI's own files use it).
VALUE_FORMAT = "{:.12e}"


@dataclass(frozen=True)
class KittiCalib:
    """The seven matrices of a KITTI calib file (see the module docstring)."""

    P0: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    P3: np.ndarray
    R0_rect: np.ndarray = field(default_factory=lambda: np.eye(3))
    Tr_velo_to_cam: np.ndarray = field(default_factory=lambda: np.hstack([VELO_TO_CAM, np.zeros((3, 1))]))
    Tr_imu_to_velo: np.ndarray = field(default_factory=lambda: np.hstack([np.eye(3), np.zeros((3, 1))]))

    def __post_init__(self) -> None:
        for key, shape in CALIB_KEYS.items():
            value = np.asarray(getattr(self, key), dtype=np.float64)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"{key} must be a finite {shape[0]}x{shape[1]} matrix, got shape {value.shape}")
            object.__setattr__(self, key, value)


def format_calib(calib: KittiCalib) -> str:
    """The file text: one ``KEY: values`` line per matrix in :data:`CALIB_KEYS` order, then a
    blank line (as KITTI's files end)."""
    lines = [f"{key}: " + " ".join(VALUE_FORMAT.format(v) for v in getattr(calib, key).ravel())
             for key in CALIB_KEYS]
    return "\n".join(lines) + "\n\n"


def write_calib(path: str | os.PathLike, calib: KittiCalib) -> None:
    """Write ``calib`` to ``path`` (ASCII)."""
    Path(path).write_text(format_calib(calib), encoding="ascii")


def read_calib(path: str | os.PathLike) -> KittiCalib:
    """Parse a KITTI calib file; DataError naming the file and line on any deviation from the
    format (missing / extra / reordered keys, wrong value count, non-numbers)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read calib file: {exc}") from None
    lines = [line for line in text.splitlines() if line.strip()]
    if len(lines) != len(CALIB_KEYS):
        raise DataError(path, f"expected {len(CALIB_KEYS)} lines ({', '.join(CALIB_KEYS)}), got {len(lines)}")
    values = {}
    for lineno, (line, (key, shape)) in enumerate(zip(lines, CALIB_KEYS.items()), start=1):
        name, sep, rest = line.partition(": ")
        if not sep or name != key:
            raise DataError(path, f"line {lineno}: expected key {key!r}, got {line[:20]!r}")
        tokens = rest.split(" ")
        if len(tokens) != shape[0] * shape[1]:
            raise DataError(path, f"line {lineno}: {key} has {len(tokens)} values, expected {shape[0] * shape[1]}")
        try:
            values[key] = np.array([float(t) for t in tokens]).reshape(shape)
        except ValueError:
            raise DataError(path, f"line {lineno}: {key} holds a value that is not a number") from None
    try:
        return KittiCalib(**values)
    except ValueError as exc:
        raise DataError(path, str(exc)) from None


def _rigid(R: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def imu_to_camera(calibration: Calibration) -> np.ndarray | None:
    """4x4 KITTI-360 IMU / GPS pose frame -> rectified camera 0 (None without
    ``calib_cam_to_pose.txt``): ``R_rect_00 @ inv(T_cam0_to_pose)``."""
    if calibration.T_cam0_to_pose is None:
        return None
    return _rigid(calibration.R_rect_00) @ np.linalg.inv(calibration.T_cam0_to_pose)


def calib_for_frame(calibration: Calibration, level: np.ndarray | None = None) -> KittiCalib:
    """The KITTI calib of a frame of a sequence with ``calibration``.

    ``level`` is the 3x3 rotation rectified camera -> level camera (:func:`.level.level_rotation`)
    when the frame is exported level, None otherwise. A camera ``P = K [I | t]`` of the rectified
    frame becomes ``K [I | level @ t]``: the same intrinsics and centre, turned level.
    """
    R = np.eye(3) if level is None else np.asarray(level, dtype=np.float64)

    def turned(P: np.ndarray) -> np.ndarray:
        K = P[:3, :3]
        t = np.linalg.solve(K, P[:3, 3])
        return np.hstack([K, (K @ (R @ t))[:, None]])

    P_left, P_right = turned(calibration.P_rect_00), turned(calibration.P_rect_01)
    velo_to_cam = _rigid(VELO_TO_CAM)
    imu = imu_to_camera(calibration)
    imu_to_velo = np.eye(4) if imu is None else np.linalg.inv(velo_to_cam) @ _rigid(R) @ imu
    return KittiCalib(P0=P_left, P1=P_right, P2=P_left, P3=P_right, R0_rect=np.eye(3),
                      Tr_velo_to_cam=velo_to_cam[:3], Tr_imu_to_velo=imu_to_velo[:3])
