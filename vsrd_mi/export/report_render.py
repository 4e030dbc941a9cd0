"""Visuals of a finished target from its result file and the dataset, for targets run without
``--vis`` (:mod:`.report`).

From ``boxes/%010d.json`` (the boxes in the target's optimisation frame) and the KITTI-360
sequence this draws what :mod:`.visualise` draws without the optimiser: the boxes projected into
the target image and a few source images (through each camera's full pose) and the bird's-eye
view with the ground truth when the dataset has it. The rendered-vs-real masks and the loss
curves need the optimised scene and the loss history, which only ``--vis`` keeps.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from ..autolabel.consensus import TargetBoxes
from ..autolabel.visualise import (
    VisualConfig,
    box_captions,
    box_colours,
    contact_sheet,
    draw_bev,
    draw_projected_boxes,
    put_text,
    scaled_intrinsics,
    scaled_size,
    write_png,
)
from ..data.kitti360 import Sequence as KittiSequence
from ..data.observations import opt_from_world
from ..geometry.boxes import Box3D


def opt_to_camera(seq: KittiSequence, target: int, frame: int) -> np.ndarray:
    """4x4 target's optimisation frame -> camera of ``frame``."""
    world_to_opt = opt_from_world(seq.cam0_to_world(target))
    return np.linalg.inv(world_to_opt @ seq.cam0_to_world(frame))


def ground_truth_in_opt(seq: KittiSequence, target: int) -> list[Box3D]:
    """Ground-truth boxes of the target frame in its optimisation frame (none without box XML)."""
    if not seq.has_boxes:
        return []
    cam_to_opt = np.linalg.inv(opt_to_camera(seq, target, target))
    return [b.transformed(cam_to_opt) for b in seq.ground_truth(target)]


def framed_image(seq: KittiSequence, tb: TargetBoxes, frame: int, scale: float, cfg: VisualConfig) -> np.ndarray:
    """Image of ``frame`` (resized by ``scale``) with the target's boxes moved to its time."""
    image = seq.image(frame)
    size = seq.calibration.image_size
    if scale != 1.0:
        image = cv2.resize(image, scaled_size(size, scale), interpolation=cv2.INTER_AREA)
    dt = float(frame - tb.target)
    moved = [b.at_offset(dt) for b in tb.boxes]
    img = draw_projected_boxes(image, moved, scaled_intrinsics(seq.calibration.K, scale), box_colours(len(moved)),
                               box_captions(moved, np.array(tb.confidences)), cfg,
                               to_cam=opt_to_camera(seq, tb.target, frame))
    put_text(img, f"frame {frame} (dt {int(dt):+d})", (6, 18), cfg.font_scale)
    return img


def spread(frames: Sequence[int], count: int) -> list[int]:
    """At most ``count`` of ``frames``, evenly spread (first and last included)."""
    frames = list(frames)
    if len(frames) <= count:
        return frames
    return [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, count).round().astype(int))]


def render_target(out_dir: Path, seq: KittiSequence, result_path: Path, sources: Sequence[int], n_sources: int,
                  cfg: VisualConfig = VisualConfig()) -> dict[str, Path]:
    """Write ``boxes_target.png``, ``boxes_sources.png`` (up to ``n_sources`` of the target's
    ``sources``) and ``bev.png`` of the target whose result file is ``result_path`` under
    ``out_dir``; returns them by name."""
    tb = TargetBoxes.read(result_path)
    files = {"boxes_target": write_png(out_dir / "boxes_target.png", framed_image(seq, tb, tb.target, 1.0, cfg))}
    sources = [f for f in spread(sources, n_sources) if f in seq.frames]
    if sources:
        sheet = contact_sheet([framed_image(seq, tb, f, cfg.sheet_scale, cfg) for f in sources], cfg.sheet_columns)
        files["boxes_sources"] = write_png(out_dir / "boxes_sources.png", sheet)
    bev = draw_bev(tb.boxes, ground_truth_in_opt(seq, tb.target), box_colours(len(tb.boxes)),
                   box_captions(tb.boxes, np.array(tb.confidences)), cfg)
    files["bev"] = write_png(out_dir / "bev.png", bev)
    return files
