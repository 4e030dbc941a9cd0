"""Glue between a KITTI-360 :class:`~vsrd_mi.data.kitti360.Sequence` and the initialisation.

:func:`stereo_frames` builds the :class:`StereoFrame` list of a target frame (poses expressed in
the target's gravity-aligned optimisation frame, :func:`vsrd_mi.data.observations.opt_from_world`);
:func:`initialise_target` runs :func:`~vsrd_mi.init.attributes.initialise` on a
:class:`~vsrd_mi.data.selection.TargetSpec`.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from ..data.kitti360 import Sequence
from ..data.observations import opt_from_world
from ..data.selection import TargetSpec
from .attributes import InstanceInit, initialise
from .config import InitConfig
from .depth import DepthDirectory
from .frames import StereoFrame


def cam_to_opt(seq: Sequence, target: int, frame: int) -> np.ndarray:
    """4x4 camera of ``frame`` -> optimisation frame of ``target``:
    ``Rx_t @ inv(cam0_to_world(t)) @ cam0_to_world(f)``."""
    return opt_from_world(seq.cam0_to_world(target)) @ seq.cam0_to_world(frame)


def stereo_frames(seq: Sequence, target: int, frames: Iterable[int],
                  instance_ids: Iterable[int] | None = None, cfg: InitConfig | None = None
                  ) -> list[StereoFrame]:
    """Stereo frames of ``frames`` (the target is added) for the initialisation of ``target``.

    Masks are the car instance masks of each frame, restricted to ``instance_ids`` when given.
    With ``cfg.depth_mode == "dir"`` the depth maps are read from ``cfg.depth_dir`` (and the right
    image is still loaded for the photometric-warp selection).
    """
    cfg = cfg or InitConfig()
    wanted = None if instance_ids is None else set(int(i) for i in instance_ids)
    directory = DepthDirectory(cfg.depth_dir) if cfg.depth_mode == "dir" else None
    calib = seq.calibration
    size = (calib.image_size[1], calib.image_size[0])
    out = []
    for f in sorted(set(frames) | {target}):
        masks = {iid: m for iid, m in seq.car_instances(f).items() if wanted is None or iid in wanted}
        depth = directory.depth(f, size) if directory is not None else None
        out.append(StereoFrame(frame_offset=f - target, left=seq.image(f, 0), right=seq.image(f, 1),
                               masks=masks, K=calib.K, baseline=calib.baseline,
                               cam_to_opt=cam_to_opt(seq, target, f), depth=depth, frame_index=f))
    return out


def initialise_target(seq: Sequence, spec: TargetSpec, cfg: InitConfig | None = None
                      ) -> dict[int, InstanceInit]:
    """Initial attributes of the target instances of ``spec`` from its target and source frames
    (instance id = KITTI-360 instance pixel value, poses in the target's optimisation frame)."""
    cfg = cfg or InitConfig()
    if cfg.depth_mode == "none":
        return {}
    frames = stereo_frames(seq, spec.target, spec.sources, spec.instance_ids, cfg)
    return initialise(frames, cfg)
