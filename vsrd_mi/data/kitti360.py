"""KITTI-360 readers: calibration, poses, images, instance maps and 3D boxes (docs/method.md §8).

Files are read directly from the KITTI-360 layout below ``root`` (no preprocessing step, no cache)::

    calibration/perspective.txt                         P_rect_00, R_rect_00, S_rect_00, P_rect_01
    calibration/calib_cam_to_pose.txt                   image_00: unrectified camera -> IMU (optional)
    data_poses/<seq>/cam0_to_world.txt                  frame + 16 floats (rectified cam0 -> world)
    data_poses/<seq>/poses.txt                          frame + 12 floats (IMU -> world)
    data_2d_raw/<seq>/image_0{0,1}/data_rect/%010d.png  8-bit RGB
    data_2d_semantics/train/<seq>/image_00/instance/%010d.png   16-bit, semanticId*1000 + instanceId
    data_3d_bboxes/train/<seq>.xml                      3D boxes (evaluation only)

Every bad input raises :class:`vsrd_mi.errors.DataError` naming the file and the problem. Per-frame
files (images, instance maps) are only opened when that frame is read, so one damaged frame does not
stop the rest of the sequence from loading.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry.boxes import Box3D, yaw_from_direction
from .labels import CAR_KITTI_ID, car_instance_value
from .masks import car_masks
from .png import read_png

#: Timestamp of static objects in the 3D-box XML (dynamic objects carry their frame index).
STATIC_TIMESTAMP = -1


def sequence_name(seq: int | str) -> str:
    """``0 -> '2013_05_28_drive_0000_sync'``; a string that is not a bare number passes through."""
    if isinstance(seq, (int, np.integer)):
        return f"2013_05_28_drive_{int(seq):04d}_sync"
    text = str(seq)
    return f"2013_05_28_drive_{int(text):04d}_sync" if text.isdigit() else text


# ----------------------------------------------------------------------------------------------
# Paths
# ----------------------------------------------------------------------------------------------


def calibration_path(root: str | Path) -> Path:
    return Path(root) / "calibration" / "perspective.txt"


def cam_to_pose_path(root: str | Path) -> Path:
    return Path(root) / "calibration" / "calib_cam_to_pose.txt"


def pose_dir(root: str | Path, sequence: int | str) -> Path:
    return Path(root) / "data_poses" / sequence_name(sequence)


def image_dir(root: str | Path, sequence: int | str, camera: int = 0) -> Path:
    return Path(root) / "data_2d_raw" / sequence_name(sequence) / f"image_{camera:02d}" / "data_rect"


def instance_dir(root: str | Path, sequence: int | str) -> Path:
    return Path(root) / "data_2d_semantics" / "train" / sequence_name(sequence) / "image_00" / "instance"


def boxes_path(root: str | Path, sequence: int | str) -> Path:
    return Path(root) / "data_3d_bboxes" / "train" / f"{sequence_name(sequence)}.xml"


def frame_file(directory: Path, frame: int) -> Path:
    """``directory / '%010d.png' % frame``."""
    return directory / f"{int(frame):010d}.png"


# ----------------------------------------------------------------------------------------------
# Calibration
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Calibration:
    """Rectified stereo calibration of one KITTI-360 sequence (all sequences share it).

    ``K`` is the left 3x3 of ``P_rect_00``; ``image_size`` is ``(width, height)``; ``baseline`` is the
    stereo baseline in metres (``-P_rect_01[0, 3] / fx``); ``T_cam0_to_pose`` maps the *unrectified*
    camera 0 to the IMU pose frame and is None when ``calib_cam_to_pose.txt`` is absent.
    """

    P_rect_00: np.ndarray
    P_rect_01: np.ndarray
    R_rect_00: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    baseline: float
    T_cam0_to_pose: np.ndarray | None = None


def _parse_floats(path: Path, lineno: int, tokens: list[str]) -> np.ndarray:
    try:
        values = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise DataError(path, f"line {lineno}: not a number in {' '.join(tokens)!r}") from None
    if not np.all(np.isfinite(values)):
        raise DataError(path, f"line {lineno}: non-finite value")
    return values


def read_key_values(path: str | Path) -> dict[str, tuple[int, list[str]]]:
    """Read ``"KEY: v1 v2 ..."`` lines (KITTI calibration text format) as ``key -> (line, tokens)``.

    Values are only converted when asked for (:func:`key_floats`), so entries such as
    ``calib_time: 09-Jan-2013 ...`` in full KITTI-360 files do not get in the way.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(path, "missing calibration file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read calibration file: {exc}") from None
    out: dict[str, tuple[int, list[str]]] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise DataError(path, f"line {lineno}: expected 'KEY: values', got {line.strip()!r}")
        key = key.strip()
        if key in out:
            raise DataError(path, f"line {lineno}: duplicate key {key!r}")
        out[key] = (lineno, rest.split())
    return out


def key_floats(path: Path, values: dict[str, tuple[int, list[str]]], key: str, count: int) -> np.ndarray:
    """The ``count`` finite numbers of ``key``; DataError naming the file, key and line otherwise."""
    if key not in values:
        raise DataError(path, f"missing key {key!r}")
    lineno, tokens = values[key]
    if len(tokens) != count:
        raise DataError(path, f"line {lineno}: key {key!r} has {len(tokens)} values, expected {count}")
    return _parse_floats(path, lineno, tokens)


def read_calibration(root: str | Path) -> Calibration:
    """Read ``calibration/perspective.txt`` (and ``calib_cam_to_pose.txt`` when present)."""
    root = Path(root)
    persp = calibration_path(root)
    values = read_key_values(persp)
    P0 = key_floats(persp, values, "P_rect_00", 12).reshape(3, 4)
    P1 = key_floats(persp, values, "P_rect_01", 12).reshape(3, 4)
    R0 = key_floats(persp, values, "R_rect_00", 9).reshape(3, 3)
    size = key_floats(persp, values, "S_rect_00", 2)
    width, height = int(round(size[0])), int(round(size[1]))
    if width <= 0 or height <= 0 or not np.allclose(size, (width, height)):
        raise DataError(persp, f"S_rect_00 must be two positive integers, got {size.tolist()}")
    fx = P0[0, 0]
    if fx <= 0 or P0[1, 1] <= 0:
        raise DataError(persp, f"P_rect_00 has non-positive focal lengths ({P0[0, 0]}, {P0[1, 1]})")
    baseline = float(-P1[0, 3] / fx)
    if baseline <= 0:
        raise DataError(persp, f"P_rect_01[0, 3] = {P1[0, 3]} gives a non-positive stereo baseline")
    T_pose = None
    pose_path = cam_to_pose_path(root)
    if pose_path.exists():
        T_pose = np.eye(4)
        T_pose[:3, :4] = key_floats(pose_path, read_key_values(pose_path), "image_00", 12).reshape(3, 4)
    return Calibration(P_rect_00=P0, P_rect_01=P1, R_rect_00=R0, K=P0[:3, :3].copy(),
                       image_size=(width, height), baseline=baseline, T_cam0_to_pose=T_pose)


# ----------------------------------------------------------------------------------------------
# Poses
# ----------------------------------------------------------------------------------------------


def read_pose_file(path: str | Path, values_per_line: int) -> dict[int, np.ndarray]:
    """Read ``"frame v1 ... vN"`` lines into 4x4 matrices (N = 16: 4x4, N = 12: 3x4 row-major).

    Raises DataError naming the line for a wrong value count, a non-finite value, a bad frame
    number or a duplicate frame.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(path, "missing pose file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read pose file: {exc}") from None
    poses: dict[int, np.ndarray] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != values_per_line + 1:
            raise DataError(path, f"line {lineno}: {len(tokens) - 1} numbers after the frame index, "
                                  f"expected {values_per_line}")
        if not tokens[0].isdigit():
            raise DataError(path, f"line {lineno}: bad frame index {tokens[0]!r}")
        frame = int(tokens[0])
        if frame in poses:
            raise DataError(path, f"line {lineno}: duplicate pose for frame {frame}")
        T = np.eye(4)
        T[:values_per_line // 4, :] = _parse_floats(path, lineno, tokens[1:]).reshape(-1, 4)
        poses[frame] = T
    return poses


def read_cam0_to_world(root: str | Path, sequence: int | str,
                       calibration: Calibration | None = None) -> dict[int, np.ndarray]:
    """Rectified camera 0 -> world for every frame with a pose.

    ``cam0_to_world.txt`` is used where it lists a frame; other frames come from ``poses.txt``
    (IMU -> world) as ``pose @ T_cam0_to_pose @ inv(R_rect_00 as 4x4)`` when the calibration has
    ``T_cam0_to_pose``. Neither file present -> DataError.
    """
    root = Path(root)
    seq = sequence_name(sequence)
    pdir = pose_dir(root, seq)
    cam_file, imu_file = pdir / "cam0_to_world.txt", pdir / "poses.txt"
    if not cam_file.exists() and not imu_file.exists():
        raise DataError(pdir, "missing pose files (neither cam0_to_world.txt nor poses.txt)")
    poses: dict[int, np.ndarray] = {}
    if imu_file.exists():
        calibration = calibration or read_calibration(root)
        if calibration.T_cam0_to_pose is None and not cam_file.exists():
            raise DataError(cam_to_pose_path(root),
                            f"missing; needed to convert {imu_file} to camera poses")
        if calibration.T_cam0_to_pose is not None:
            R_rect = np.eye(4)
            R_rect[:3, :3] = calibration.R_rect_00
            to_cam = calibration.T_cam0_to_pose @ np.linalg.inv(R_rect)
            poses = {f: T @ to_cam for f, T in read_pose_file(imu_file, 12).items()}
    if cam_file.exists():
        poses.update(read_pose_file(cam_file, 16))
    return dict(sorted(poses.items()))


# ----------------------------------------------------------------------------------------------
# 3D boxes
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WorldBox:
    """One element of the 3D-box XML: a box in KITTI-360 world coordinates (z up).

    ``transform`` maps the unit box template (local x = length, y = width, z = height, +-0.5) to
    world; ``timestamp`` is the frame index for dynamic objects and -1 for static ones.
    """

    instance_id: int
    kitti_id: int
    transform: np.ndarray
    start_frame: int
    end_frame: int
    timestamp: int

    @property
    def dynamic(self) -> bool:
        return self.timestamp != STATIC_TIMESTAMP

    @property
    def centre(self) -> np.ndarray:
        return self.transform[:3, 3]

    @property
    def size_lwh(self) -> np.ndarray:
        """Full (length, width, height): the column norms of the transform's linear part."""
        return np.linalg.norm(self.transform[:3, :3], axis=0)

    @property
    def length_axis(self) -> np.ndarray:
        return self.transform[:3, 0] / self.size_lwh[0]


def _xml_text(path: Path, obj: ET.Element, tag: str) -> str:
    child = obj.find(tag)
    if child is None or child.text is None or not child.text.strip():
        raise DataError(path, f"object <{obj.tag}> has no <{tag}>")
    return child.text.strip()


def _xml_int(path: Path, obj: ET.Element, tag: str) -> int:
    text = _xml_text(path, obj, tag)
    try:
        return int(text)
    except ValueError:
        raise DataError(path, f"object <{obj.tag}>: <{tag}> is not an integer: {text!r}") from None


def _xml_matrix(path: Path, obj: ET.Element, tag: str) -> np.ndarray:
    node = obj.find(tag)
    if node is None:
        raise DataError(path, f"object <{obj.tag}> has no <{tag}>")
    rows, cols = _xml_int(path, node, "rows"), _xml_int(path, node, "cols")
    try:
        data = np.array([float(t) for t in _xml_text(path, node, "data").split()])
    except ValueError:
        raise DataError(path, f"object <{obj.tag}>: <{tag}> data is not numeric") from None
    if data.size != rows * cols:
        raise DataError(path, f"object <{obj.tag}>: <{tag}> has {data.size} values, "
                              f"expected {rows}x{cols}")
    if not np.all(np.isfinite(data)):
        raise DataError(path, f"object <{obj.tag}>: <{tag}> has non-finite values")
    return data.reshape(rows, cols)


def read_world_boxes(path: str | Path) -> list[WorldBox]:
    """Parse every object of a KITTI-360 ``data_3d_bboxes`` XML file (all classes)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise DataError(path, "missing 3D box file") from None
    except ET.ParseError as exc:
        raise DataError(path, f"malformed XML: {exc}") from None
    boxes = []
    for obj in root:
        if obj.find("transform") is None:
            continue  # not an object element (KITTI-360 files hold only objects, but be lenient)
        T = _xml_matrix(path, obj, "transform")
        if T.shape != (4, 4):
            raise DataError(path, f"object <{obj.tag}>: transform is {T.shape[0]}x{T.shape[1]}, expected 4x4")
        box = WorldBox(instance_id=_xml_int(path, obj, "instanceId"),
                       kitti_id=_xml_int(path, obj, "semanticId"), transform=T,
                       start_frame=_xml_int(path, obj, "start_frame"),
                       end_frame=_xml_int(path, obj, "end_frame"),
                       timestamp=_xml_int(path, obj, "timestamp"))
        if np.any(box.size_lwh <= 0):
            raise DataError(path, f"object <{obj.tag}>: degenerate transform (zero box extent)")
        boxes.append(box)
    return boxes


def _world_velocity(track: dict[int, WorldBox], frame: int) -> np.ndarray:
    """Velocity (metres per frame index, world) of a dynamic object from its neighbouring elements.

    Central difference between the nearest elements before and after ``frame`` when both exist,
    otherwise one-sided with the element at ``frame``; zero for a single element.
    """
    before = [f for f in track if f < frame]
    after = [f for f in track if f > frame]
    a = max(before) if before else frame
    b = min(after) if after else frame
    if a == b:
        return np.zeros(3)
    return (track[b].centre - track[a].centre) / (b - a)


def boxes_in_camera(world_boxes: list[WorldBox], frame: int, cam0_to_world: np.ndarray) -> list[Box3D]:
    """Car boxes present at ``frame``, in that frame's rectified camera coordinates.

    Static objects count when ``start_frame <= frame <= end_frame``; dynamic objects when they have
    an element with ``timestamp == frame``. Size ``(w, h, l)``; yaw from the length axis projected to
    the camera x-z plane; velocity in metres per frame index (dynamic objects only).

    The centre is exact. The orientation follows the KITTI label convention (vertical box axis =
    camera y), so the camera's pitch and roll relative to gravity (a few degrees on KITTI-360) are
    dropped from the orientation, as in :meth:`Box3D.transformed`.
    """
    world_to_cam = np.linalg.inv(cam0_to_world)
    R = world_to_cam[:3, :3]
    tracks: dict[tuple[int, int], dict[int, WorldBox]] = {}  # (class, instance) -> frame -> element
    for b in world_boxes:
        if b.dynamic:
            tracks.setdefault((b.kitti_id, b.instance_id), {})[b.timestamp] = b
    out = []
    for b in world_boxes:
        if b.kitti_id != CAR_KITTI_ID:
            continue
        if b.dynamic:
            if b.timestamp != frame:
                continue
            velocity = R @ _world_velocity(tracks[(b.kitti_id, b.instance_id)], frame)
        else:
            if not b.start_frame <= frame <= b.end_frame:
                continue
            velocity = np.zeros(3)
        length, width, height = b.size_lwh
        out.append(Box3D(centre=R @ b.centre + world_to_cam[:3, 3],
                         size=(width, height, length),
                         yaw=yaw_from_direction(R @ b.length_axis),
                         velocity=velocity, dynamic=b.dynamic,
                         instance_id=car_instance_value(b.instance_id)))
    return out


# ----------------------------------------------------------------------------------------------
# Sequence
# ----------------------------------------------------------------------------------------------

_FRAME_PNG = re.compile(r"^(\d{10})\.png$")


def frames_in(directory: Path) -> set[int]:
    """Frame indices of the ``%010d.png`` files in ``directory``; DataError when it cannot be listed."""
    try:
        names = [p.name for p in directory.iterdir()]
    except OSError as exc:
        raise DataError(directory, f"cannot list directory: {exc.strerror or exc}") from None
    return {int(m.group(1)) for name in names if (m := _FRAME_PNG.match(name))}


class Sequence:
    """One KITTI-360 sequence below ``root``.

    ``frames`` lists (sorted) the frames with both a pose and a left image; per-frame files are
    read lazily so that a damaged image only fails when that frame is read.
    """

    def __init__(self, root: str | Path, sequence: int | str):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataError(self.root, "missing dataset directory")
        self.name = sequence_name(sequence)
        self.calibration = read_calibration(self.root)
        self._poses = read_cam0_to_world(self.root, self.name, self.calibration)
        left_dir = self.image_dir(0)
        if not left_dir.is_dir():
            raise DataError(left_dir, "missing image directory")
        with_image = frames_in(left_dir)
        self.frames: list[int] = sorted(with_image & self._poses.keys())

    # -- paths -------------------------------------------------------------------------------

    def image_dir(self, camera: int = 0) -> Path:
        return image_dir(self.root, self.name, camera)

    def image_path(self, frame: int, camera: int = 0) -> Path:
        return frame_file(self.image_dir(camera), frame)

    @property
    def instance_dir(self) -> Path:
        return instance_dir(self.root, self.name)

    def instance_path(self, frame: int) -> Path:
        return frame_file(self.instance_dir, frame)

    @property
    def boxes_path(self) -> Path:
        return boxes_path(self.root, self.name)

    # -- availability ------------------------------------------------------------------------

    @property
    def has_masks(self) -> bool:
        """Whether the sequence has a 2D instance-map directory."""
        return self.instance_dir.is_dir()

    @property
    def has_boxes(self) -> bool:
        """Whether the sequence has a 3D-box XML file."""
        return self.boxes_path.is_file()

    @cached_property
    def mask_frames(self) -> list[int]:
        """Frames of :attr:`frames` that have an instance-map file (not yet checked for damage)."""
        if not self.has_masks:
            return []
        names = frames_in(self.instance_dir)
        return [f for f in self.frames if f in names]

    # -- per-frame data ------------------------------------------------------------------------

    def _check_frame(self, frame: int) -> None:
        if frame not in self._poses:
            raise DataError(pose_dir(self.root, self.name), f"no pose for frame {frame}")

    def cam0_to_world(self, frame: int) -> np.ndarray:
        """4x4 rectified camera 0 -> world of ``frame`` (a copy)."""
        self._check_frame(frame)
        return self._poses[frame].copy()

    def image(self, frame: int, camera: int = 0) -> np.ndarray:
        """uint8 HxWx3 RGB rectified image of ``camera`` (0 left, 1 right)."""
        self._check_frame(frame)
        return read_png(self.image_path(frame, camera), dtype=np.uint8, channels=3,
                        size=self.calibration.image_size, what=f"image_{camera:02d} image")

    def instance_map(self, frame: int) -> np.ndarray:
        """uint16 HxW instance map (``semanticId * 1000 + instanceId``)."""
        self._check_frame(frame)
        return read_png(self.instance_path(frame), dtype=np.uint16, channels=1,
                        size=self.calibration.image_size, what="instance map")

    def car_instances(self, frame: int) -> dict[int, np.ndarray]:
        """Boolean HxW mask of every car in ``frame``, keyed by pixel value (26001..26999)."""
        return car_masks(self.instance_map(frame))

    @cached_property
    def _world_boxes(self) -> list[WorldBox]:
        return read_world_boxes(self.boxes_path)

    def ground_truth(self, frame: int) -> list[Box3D]:
        """Ground-truth car boxes of ``frame`` in its rectified camera frame (evaluation only)."""
        return boxes_in_camera(self._world_boxes, frame, self.cam0_to_world(frame))
