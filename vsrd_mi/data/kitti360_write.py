"""Writers for the KITTI-360 layout read by :mod:`vsrd_mi.data.kitti360` (docs/method.md §8).

They write exactly what the readers accept, so code that produces data (tests, synthetic scenes)
and the loader share one description of the format.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Iterable, Mapping

import cv2
import numpy as np

from .kitti360 import (STATIC_TIMESTAMP, WorldBox, boxes_path, calibration_path, cam_to_pose_path,
                       frame_file, image_dir, instance_dir, pose_dir)

#: Unit box template of the XML ``vertices`` (KITTI-360 raw vertex order, halves of l, w, h).
UNIT_VERTICES = 0.5 * np.array([
    [+1, +1, +1], [+1, +1, -1], [+1, -1, +1], [+1, -1, -1],
    [-1, +1, -1], [-1, +1, +1], [-1, -1, -1], [-1, -1, +1]], dtype=np.float64)
#: The 12 triangles of the box template (indices into :data:`UNIT_VERTICES`).
UNIT_FACES = np.array([
    [0, 2, 3], [0, 3, 1], [4, 6, 7], [4, 7, 5], [0, 1, 4], [0, 4, 5],
    [2, 7, 6], [2, 6, 3], [0, 5, 7], [0, 7, 2], [1, 3, 6], [1, 6, 4]], dtype=np.int64)


def _fmt(values: Iterable[float]) -> str:
    return " ".join(f"{float(v):.9e}" for v in values)


def write_calibration(root: str | Path, K: np.ndarray, image_size: tuple[int, int], baseline: float,
                      R_rect_00: np.ndarray | None = None, T_cam0_to_pose: np.ndarray | None = None) -> None:
    """Write ``calibration/perspective.txt`` (and ``calib_cam_to_pose.txt`` when given)."""
    path = calibration_path(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    P0 = np.zeros((3, 4))
    P0[:, :3] = K
    P1 = P0.copy()
    P1[0, 3] = -K[0, 0] * baseline
    R = np.eye(3) if R_rect_00 is None else np.asarray(R_rect_00)
    W, H = image_size
    path.write_text(f"S_rect_00: {_fmt((W, H))}\nR_rect_00: {_fmt(R.ravel())}\nP_rect_00: {_fmt(P0.ravel())}\n"
                    f"S_rect_01: {_fmt((W, H))}\nR_rect_01: {_fmt(R.ravel())}\nP_rect_01: {_fmt(P1.ravel())}\n")
    if T_cam0_to_pose is not None:
        cam_to_pose_path(root).write_text(f"image_00: {_fmt(np.asarray(T_cam0_to_pose)[:3].ravel())}\n")


def write_cam0_to_world(root: str | Path, sequence: int | str, poses: Mapping[int, np.ndarray]) -> Path:
    """Write ``data_poses/<seq>/cam0_to_world.txt`` ("frame" + 16 floats per line)."""
    path = pose_dir(root, sequence) / "cam0_to_world.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{f} {_fmt(np.asarray(T).ravel())}\n" for f, T in sorted(poses.items())))
    return path


def write_imu_poses(root: str | Path, sequence: int | str, poses: Mapping[int, np.ndarray]) -> Path:
    """Write ``data_poses/<seq>/poses.txt`` ("frame" + 12 floats per line, IMU -> world)."""
    path = pose_dir(root, sequence) / "poses.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{f} {_fmt(np.asarray(T)[:3].ravel())}\n" for f, T in sorted(poses.items())))
    return path


def write_image(root: str | Path, sequence: int | str, frame: int, rgb: np.ndarray, camera: int = 0) -> Path:
    """Write an 8-bit RGB image to ``data_2d_raw/<seq>/image_0<camera>/data_rect/``."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected uint8 HxWx3 RGB, got {rgb.dtype} {rgb.shape}")
    path = frame_file(image_dir(root, sequence, camera), frame)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: cannot write image")
    return path


def write_instance_map(root: str | Path, sequence: int | str, frame: int, instance_map: np.ndarray) -> Path:
    """Write a uint16 instance map (``semanticId * 1000 + instanceId``) as a 16-bit PNG."""
    instance_map = np.asarray(instance_map)
    if instance_map.dtype != np.uint16 or instance_map.ndim != 2:
        raise ValueError(f"expected uint16 HxW, got {instance_map.dtype} {instance_map.shape}")
    path = frame_file(instance_dir(root, sequence), frame)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), instance_map):
        raise OSError(f"{path}: cannot write instance map")
    return path


def _matrix(parent: ET.Element, tag: str, m: np.ndarray, dt: str) -> None:
    node = ET.SubElement(parent, tag, type_id="opencv-matrix")
    ET.SubElement(node, "rows").text = str(m.shape[0])
    ET.SubElement(node, "cols").text = str(m.shape[1])
    ET.SubElement(node, "dt").text = dt
    ET.SubElement(node, "data").text = " ".join(str(v) if dt == "u" else repr(float(v)) for v in m.ravel())


def world_box(instance_id: int, kitti_id: int, centre: np.ndarray, size_lwh: np.ndarray, heading_yaw: float,
              start_frame: int, end_frame: int, timestamp: int = STATIC_TIMESTAMP) -> WorldBox:
    """A z-up world box with its length axis at angle ``heading_yaw`` from world +x (about +z)."""
    c, s = np.cos(heading_yaw), np.sin(heading_yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R @ np.diag(np.asarray(size_lwh, dtype=np.float64))
    T[:3, 3] = centre
    return WorldBox(instance_id=instance_id, kitti_id=kitti_id, transform=T, start_frame=start_frame,
                    end_frame=end_frame, timestamp=timestamp)


def write_boxes_xml(root: str | Path, sequence: int | str, boxes: Iterable[WorldBox],
                    labels: Mapping[int, str] | None = None) -> Path:
    """Write ``data_3d_bboxes/train/<seq>.xml``; ``labels`` maps KITTI ids to names (default "car")."""
    path = boxes_path(root, sequence)
    path.parent.mkdir(parents=True, exist_ok=True)
    top = ET.Element("opencv_storage")
    for index, b in enumerate(boxes):
        obj = ET.SubElement(top, f"object{index + 1}")
        ET.SubElement(obj, "label").text = (labels or {}).get(b.kitti_id, "car")
        _matrix(obj, "vertices", UNIT_VERTICES, "f")
        _matrix(obj, "faces", UNIT_FACES, "u")
        _matrix(obj, "transform", b.transform, "d")
        for tag, value in (("index", index), ("semanticId", b.kitti_id), ("instanceId", b.instance_id),
                           ("timestamp", b.timestamp), ("dynamic", int(b.dynamic)),
                           ("start_frame", b.start_frame), ("end_frame", b.end_frame)):
            ET.SubElement(obj, tag).text = str(value)
    ET.indent(top)
    path.write_text('<?xml version="1.0"?>\n' + ET.tostring(top, encoding="unicode") + "\n")
    return path
