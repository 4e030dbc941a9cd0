"""Whether the views that label a car see its length at all.

A mask-box projection loss measures a car's length only through views in which moving the car's
far end moves its 2D box. A car straight ahead in the ego lane, seen from inside the strip its
sides span, shows only its rear in every view: its far end lies behind its near face, and no
view's mask changes with its length (docs/accuracy.md, "Lengths no view sees"). Such a car's
length is not measured by the masks of any method that fits boxes to them, and its label's
length is whatever the labeller assumed.

:func:`length_view_shift` measures this from the ground truth: over the frames that label a car,
the most its 2D box (the projected corners of its true box, clipped to the image) moves when its
far end, the one farther from that frame's camera, moves out by ``probe`` metres. Occluders are
not taken into account (a parked car whose far end a neighbour hides has its own breakdown,
occlusion). The evaluation takes the frames the default target selection picks for the
evaluated frame (:func:`~vsrd_mi.data.selection.spec_for_frame`), which for a target are the
frames that labelled it.
"""

from __future__ import annotations

import dataclasses
from typing import Iterable

import numpy as np

from ..data.kitti360 import Sequence
from ..data.selection import SelectionConfig, spec_for_frame
from ..errors import DataError
from ..geometry.boxes import Box3D
from ..geometry.camera import box_to_2d

#: How far the far end moves out (m): a tenth of a car's length.
LENGTH_PROBE_M = 0.5
#: A view sees a length when the probe moves the car's 2D box by at least this much (px): one
#: pixel of a mask.
LENGTH_SEEN_PX = 1.0


def far_end_shift(box: Box3D, K: np.ndarray, image_size: tuple[int, int], probe: float = LENGTH_PROBE_M
                  ) -> float | None:
    """How far (px, the largest of the four sides) ``box``'s 2D box (camera frame, clipped to the
    image) moves when its end farther from the camera moves out by ``probe`` metres; None when
    the box is not in the image."""
    if probe <= 0:
        raise ValueError(f"far_end_shift: probe must be > 0 m, got {probe}")
    axis = box.rotation[:, 2]
    sign = 1.0 if float(np.dot(axis, box.centre)) >= 0.0 else -1.0  # the end at +axis is farther
    size = np.array(box.size, dtype=np.float64)
    size[2] += probe
    longer = dataclasses.replace(box, centre=np.asarray(box.centre) + sign * 0.5 * probe * axis, size=size)
    before, after = box_to_2d(box, K, image_size=image_size), box_to_2d(longer, K, image_size=image_size)
    if before is None or after is None:
        return None
    return float(np.max(np.abs(after - before)))


def length_view_shift(seq: Sequence, frame: int, instance_ids: Iterable[int], probe: float = LENGTH_PROBE_M,
                      selection: SelectionConfig | None = None, cache: dict | None = None) -> dict[int, float]:
    """Per ground-truth car of ``frame`` (instance-map values ``instance_ids``): the largest
    :func:`far_end_shift` over ``frame`` and the sources :func:`spec_for_frame` picks for it (0
    where no frame shows the car). Without a selection (too few sources) only ``frame`` counts.
    ``cache`` (frame -> ground-truth boxes) may be shared between calls on one sequence."""
    cache = {} if cache is None else cache
    try:
        frames = [frame] + [int(f) for f in spec_for_frame(seq, frame, selection).sources]
    except DataError:
        frames = [frame]
    K, size = seq.calibration.K, seq.calibration.image_size
    wanted = set(int(i) for i in instance_ids)
    shifts = dict.fromkeys(wanted, 0.0)
    for f in frames:
        if f not in cache:
            cache[f] = {b.instance_id: b for b in seq.ground_truth(f)}
        for iid in wanted & cache[f].keys():
            shift = far_end_shift(cache[f][iid], K, size, probe)
            if shift is not None:
                shifts[iid] = max(shifts[iid], shift)
    return shifts


__all__ = ["LENGTH_PROBE_M", "LENGTH_SEEN_PX", "far_end_shift", "length_view_shift"]
