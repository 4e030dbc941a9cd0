"""Synthetic KITTI-360 sequences: posed stereo frames, exact instance masks and 3D boxes.

:func:`generate_sequence` lays out a street (:mod:`~vsrd_mi.synth.world`), ray-casts both
rectified cameras of every frame with Mitsuba (:mod:`~vsrd_mi.synth.render`) and writes the
KITTI-360 release layout::

    calibration/perspective.txt, calibration/calib_cam_to_pose.txt
    data_poses/<seq>/cam0_to_world.txt, data_poses/<seq>/poses.txt
    data_2d_raw/<seq>/image_0{0,1}/data_rect/%010d.png
    data_2d_semantics/train/<seq>/image_00/instance/%010d.png
    data_3d_bboxes/train/<seq>.xml
    data_3d_bboxes/train/<seq>.attributes.json   (vsrd-mi's own: :mod:`.attributes`)

with ``<seq> = 2013_05_28_drive_%04d_sync``. The returned :class:`SynthSummary` holds the ground
truth boxes in every frame's rectified camera frame, as a loader of these files should find them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from ..data.kitti360 import CAR_KITTI_ID, STATIC_TIMESTAMP, frame_file, image_dir, instance_dir
from ..data.kitti360_write import (world_box, write_boxes_xml, write_calibration,
                                   write_cam0_to_world, write_imu_poses)
from ..geometry.boxes import Box3D
from .attributes import AmodalCaster, write_attributes
from .config import SynthConfig
from .render import RayCaster, View, render_view
from .layout import build_world
from .world import SynthWorld


@dataclass
class SynthSummary:
    """What :func:`generate_sequence` wrote, and the ground truth it implies."""

    root: Path
    sequence: str
    frames: list[int]
    #: Ground-truth boxes per frame number, in that frame's rectified cam0 coordinates
    #: (``instance_id`` = 26 * 1000 + instanceId; velocity in metres per frame index).
    boxes: dict[int, list[Box3D]]
    world: SynthWorld
    #: Wall-clock seconds spent (layout, rendering and writing).
    seconds: float

    def instance_ids(self) -> list[int]:
        return [car.global_id for car in self.world.cars]


def write_annotations(root: Path, world: SynthWorld) -> None:
    """Calibration, both pose files and the 3D-box XML, through :mod:`.kitti360_write`.

    The XML holds one element per parked car (timestamp -1, start/end frame covering the
    sequence) and one element per frame for every moving car (timestamp = frame number).
    """
    rig = world.rig
    write_calibration(root, rig.K, rig.image_size, rig.baseline, rig.r_rect_00, rig.cam0_to_pose)
    write_cam0_to_world(root, world.sequence, dict(zip(world.frames, world.cam0_to_world)))
    write_imu_poses(root, world.sequence, dict(zip(world.frames, world.poses)))
    first, last = world.frames[0], world.frames[-1]
    boxes = []
    for car in world.cars:
        stamps = list(enumerate(world.frames)) if car.dynamic else [(0, STATIC_TIMESTAMP)]
        boxes += [world_box(car.instance_id, CAR_KITTI_ID, car.centre(i), car.size_lwh, car.yaw,
                            first, last, stamp) for i, stamp in stamps]
    write_boxes_xml(root, world.sequence, boxes)


def write_png(path: Path, image: np.ndarray, compression: int) -> None:
    """Write an image with OpenCV (BGR order for colour, uint16 for instance maps) as PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]):
        raise OSError(f"{path}: OpenCV could not write the PNG")


def render_frame(world: SynthWorld, i: int) -> tuple[View, View]:
    """Left and right views of frame index ``i`` (the right view's instance map is unused)."""
    mesh = world.frame_mesh(i)
    caster = RayCaster(mesh.vertices, mesh.faces)
    return render_view(world, mesh, caster, i, 0), render_view(world, mesh, caster, i, 1)


def generate_sequence(out_root: str | Path, seq: int = 0, frames: int = 60, n_static: int = 4,
                      n_dynamic: int = 2, seed: int = 0, meshes: Sequence[str | Path] | None = None,
                      config: SynthConfig = SynthConfig(),
                      progress: Callable[[int, int], None] | None = None) -> SynthSummary:
    """Write a complete synthetic KITTI-360 sequence under ``out_root`` (deterministic by seed).

    ``meshes`` are car mesh files (None: the bundled CC0 meshes; an empty list: procedural cars
    only). ``progress(done, total)`` is called after each frame.
    """
    start = time.perf_counter()
    root = Path(out_root)
    world = build_world(seq, frames, n_static, n_dynamic, seed, meshes, config)
    write_annotations(root, world)
    level = config.png_compression
    amodal = AmodalCaster(world)
    visibility = {}
    for i, frame in enumerate(world.frames):
        left, right = render_frame(world, i)
        for camera, view in ((0, left), (1, right)):
            write_png(frame_file(image_dir(root, world.sequence, camera), frame),
                      view.rgb[:, :, ::-1], level)
        write_png(frame_file(instance_dir(root, world.sequence), frame), left.instance, level)
        visibility[frame] = amodal.frame(i, left.instance)
        if progress is not None:
            progress(i + 1, len(world.frames))
    write_attributes(root, world, visibility)
    boxes = {frame: world.boxes_in_camera(i) for i, frame in enumerate(world.frames)}
    return SynthSummary(root, world.sequence, list(world.frames), boxes, world,
                        time.perf_counter() - start)


__all__ = ["SynthConfig", "SynthSummary", "generate_sequence", "render_frame", "write_annotations",
           "write_png"]
