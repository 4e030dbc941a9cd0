"""Everything the optimiser needs about one target frame, in the optimisation frame.

Optimisation frame (docs/method.md §1): the target camera rotated about its x axis so that its y axis is
gravity-aligned (pitch removed, roll kept); x right, y down, z forward, origin at the target camera
centre. KITTI-360's world is z-up, so "down" is world ``-z``.

:func:`load_observations` gathers for every frame of a :class:`~vsrd_mi.data.selection.TargetSpec`
(target first, then the other source and group frames in frame order) the camera, the frame offset
and per target instance its mask, tight 2D box and visibility, plus a soft ray-sampling weight map.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry.boxes import Box3D
from ..geometry.camera import LENGTH_PROBE_M, box_to_2d, far_end_shift
from .kitti360 import Sequence
from .masks import (SOFT_WEIGHT_SCALE_PX, lowest_rows, occluder_map, open_sides, passes_size_filter,
                    soft_weight, tight_box)
from .selection import SelectionConfig, TargetSpec

#: World "up" of KITTI-360 (z-up world).
WORLD_UP = np.array([0.0, 0.0, 1.0])


def rotation_x(angle: float) -> np.ndarray:
    """Right-handed rotation by ``angle`` (radians) about the x axis."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def gravity_rotation(cam_to_world: np.ndarray, world_up: np.ndarray = WORLD_UP) -> np.ndarray:
    """Rotation ``Rx`` about the camera x axis that makes gravity lie in the camera's x-y plane.

    With ``down`` the world's down direction in camera coordinates, ``Rx @ down`` has zero z and
    positive y: the camera pitch is removed, its roll (the x component) kept.
    """
    down = -np.asarray(cam_to_world, dtype=np.float64)[:3, :3].T @ np.asarray(world_up, dtype=np.float64)
    return rotation_x(float(np.arctan2(-down[2], down[1])))


def opt_from_world(cam_to_world_target: np.ndarray, world_up: np.ndarray = WORLD_UP) -> np.ndarray:
    """4x4 world -> optimisation frame of a target camera (``Rx @ inv(cam_to_world)``)."""
    T = np.eye(4)
    T[:3, :3] = gravity_rotation(cam_to_world_target, world_up)
    return T @ np.linalg.inv(cam_to_world_target)


@dataclass(frozen=True)
class ObservationConfig:
    """How masks become supervision."""

    #: Length scale (px) of the soft sampling weight ``sigmoid(signed distance / scale)`` (docs/method.md §3).
    soft_weight_scale_px: float = SOFT_WEIGHT_SCALE_PX
    #: Size filter deciding whether an instance counts as *visible* in a frame (its 2D box then
    #: supervises the projection loss); the same thresholds as target selection.
    selection: SelectionConfig = field(default_factory=SelectionConfig)


@dataclass
class Observations:
    """One target frame's supervision (F frames, N target instances, images H x W).

    Frame 0 is the target; the others are its sources and group frames in frame order
    (``is_source`` / ``in_group`` tell which, a frame may be both). All poses are relative to the
    optimisation frame of the target. The calibration is shared by all frames of a KITTI-360
    sequence, so ``K`` is repeated per frame and ``image_size`` is one ``(W, H)``.
    """

    sequence: str
    target: int
    #: (F,) frame indices, target first.
    frames: np.ndarray
    #: (F,) frame offsets ``frame - target`` (int), the time of that frame's rays.
    dt: np.ndarray
    #: (F, 4, 4) OpenCV camera -> optimisation frame.
    cam_to_opt: np.ndarray
    #: (F, 3, 3) intrinsics.
    K: np.ndarray
    #: ``(width, height)`` of every image.
    image_size: tuple[int, int]
    #: (N,) target instance values (26001..26999) in the order used by every per-instance array.
    instance_ids: np.ndarray
    #: (F, N, H, W) bool instance masks (all False where the instance is absent).
    masks: np.ndarray
    #: (F, N, 4) tight 2D boxes ``(x1, y1, x2, y2)`` in pixel-centre convention; NaN where absent.
    boxes2d: np.ndarray
    #: (F, N) whether the instance passes the size filter in that frame (supervises its 2D box).
    visible: np.ndarray
    #: (F, N, 4) the sides (left, top, right, bottom) of each mask box that an occluder or the
    #: image edge may cut short (:func:`~vsrd_mi.data.masks.open_sides`).
    open_sides: np.ndarray
    #: (F, H, W) float32 soft ray-sampling weights (max over instances, see :func:`soft_weight`).
    weights: np.ndarray
    #: (F,) whether the frame is one of the target's source frames.
    is_source: np.ndarray
    #: (F,) whether the frame belongs to the target's group (boxes shared with it).
    in_group: np.ndarray
    #: 4x4 world -> optimisation frame.
    T_opt_from_world: np.ndarray
    #: Left (image_00) and right (image_01) image paths per frame, for stereo initialisation.
    image_paths_left: list[Path]
    image_paths_right: list[Path]
    #: Stereo baseline (m); the right camera is the left one shifted by +baseline along x.
    baseline: float
    #: The selection result these observations were built from.
    spec: TargetSpec | None = None

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def num_instances(self) -> int:
        return len(self.instance_ids)


def frame_order(spec: TargetSpec) -> list[int]:
    """Target first, then every other source / group frame in increasing order."""
    rest = sorted((set(spec.sources) | set(spec.group)) - {spec.target})
    return [spec.target, *rest]


def load_observations(seq: Sequence, spec: TargetSpec,
                      cfg: ObservationConfig | None = None) -> Observations:
    """Read masks, cameras and poses of ``spec``'s frames into an :class:`Observations`."""
    cfg = cfg or ObservationConfig()
    sel = cfg.selection
    frames = frame_order(spec)
    ids = list(spec.instance_ids)
    T_opt_world = opt_from_world(seq.cam0_to_world(spec.target))
    W, H = seq.calibration.image_size
    F, N = len(frames), len(ids)
    masks = np.zeros((F, N, H, W), dtype=bool)
    boxes = np.full((F, N, 4), np.nan)
    visible = np.zeros((F, N), dtype=bool)
    sides = np.zeros((F, N, 4), dtype=bool)
    weights = np.zeros((F, H, W), dtype=np.float32)
    cam_to_opt = np.zeros((F, 4, 4))
    for i, f in enumerate(frames):
        cam_to_opt[i] = T_opt_world @ seq.cam0_to_world(f)
        instance_map = seq.instance_map(f)
        occluders, lowest = occluder_map(instance_map), lowest_rows(instance_map)
        for n, v in enumerate(ids):
            m = instance_map == v
            masks[i, n] = m
            box = tight_box(m)
            if box is not None:
                boxes[i, n] = box
                visible[i, n] = passes_size_filter(m, sel.min_mask_area, sel.min_box_side)
                sides[i, n] = open_sides(m, occluders, lowest)
        weights[i] = soft_weight(masks[i], cfg.soft_weight_scale_px)
    return Observations(
        sequence=seq.name, target=spec.target, frames=np.array(frames, dtype=np.int64),
        dt=np.array(frames, dtype=np.int64) - spec.target, cam_to_opt=cam_to_opt,
        K=np.repeat(seq.calibration.K[None], F, axis=0), image_size=(W, H),
        instance_ids=np.array(ids, dtype=np.int64), masks=masks, boxes2d=boxes, visible=visible,
        open_sides=sides,
        weights=weights, is_source=np.array([f in spec.sources for f in frames]),
        in_group=np.array([f in spec.group for f in frames]), T_opt_from_world=T_opt_world,
        image_paths_left=[seq.image_path(f, 0) for f in frames],
        image_paths_right=[seq.image_path(f, 1) for f in frames],
        baseline=seq.calibration.baseline, spec=spec)

def box_in_frame(box: Box3D, obs: Observations, f: int) -> Box3D:
    """Box (optimisation frame, target time) expressed in frame ``f``'s camera at its time.

    The camera may be pitched: the result keeps only the heading's yaw about the camera's y
    axis (what a KITTI label can hold). Project with :func:`footprint_in_frame`, not this box.
    """
    return box.at_offset(float(obs.dt[f])).transformed(np.linalg.inv(obs.cam_to_opt[f]))


def length_view_px(box: Box3D, obs: Observations, frames, probe: float = LENGTH_PROBE_M) -> float:
    """The most, over ``frames`` (indices into ``obs``), that the box's 2D box moves when its far
    end moves out by ``probe`` metres (:func:`~vsrd_mi.geometry.camera.far_end_shift` through
    each frame's full camera pose, at its time; 0 where it is out of view): how well those views
    measure the box's length."""
    shifts = [far_end_shift(box, obs.K[f], obs.image_size, probe, world_to_cam=np.linalg.inv(obs.cam_to_opt[f]),
                            dt=float(obs.dt[f])) for f in np.asarray(frames, dtype=np.int64)]
    return max((s for s in shifts if s is not None), default=0.0)


def footprint_in_frame(box: Box3D, obs: Observations, f: int) -> np.ndarray | None:
    """2D footprint of the box (optimisation frame, target time) in frame ``f``'s image: the
    exact projection through the full camera pose (a pitched camera included)."""
    return box_to_2d(box, obs.K[f], world_to_cam=np.linalg.inv(obs.cam_to_opt[f]),
                     image_size=obs.image_size, dt=float(obs.dt[f]))
