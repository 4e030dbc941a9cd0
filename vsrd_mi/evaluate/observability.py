"""Whether the views that label a car see its length at all.

A mask-box projection loss measures a car's length only through views in which moving the car's
far end moves its 2D box. A car straight ahead in the ego lane, seen from inside the strip its
sides span, shows only its rear in every view: its far end lies behind its near face, and no
view's mask changes with its length beyond a fraction of a pixel at the roof line
(docs/accuracy.md, "What is still short"). Its length is not measured by the masks of any method
that fits boxes to them, and its label's length is whatever the labeller assumed.

:func:`length_view_shift` measures this from the ground truth: over a set of frames, the most a
car's 2D box (the projected corners of its true box, clipped to the image) moves when its far
end, the one farther from that frame's camera, moves out by ``probe`` metres. Occluders are not
taken into account (a parked car whose far end a neighbour hides has its own breakdown,
occlusion). :func:`~vsrd_mi.geometry.camera.far_end_shift` measures one view (the optimisation
uses it on its initial boxes to find the lengths no view measures). :func:`labelling_frames`
gives the frames: those the default target selection picks around the evaluated frame
(:func:`~vsrd_mi.data.selection.spec_for_frame`: its sources and its group), which for a target
are the views that labelled it and for a group frame the views of a target beside it.
"""

from __future__ import annotations

from typing import Iterable

from ..data.kitti360 import Sequence
from ..data.selection import SelectionConfig, TooFewSourcesError, spec_for_frame
from ..geometry.boxes import Box3D
from ..geometry.camera import LENGTH_PROBE_M, far_end_shift


def labelling_frames(seq: Sequence, frame: int, selection: SelectionConfig | None = None) -> list[int] | None:
    """``frame``, its sources and its group under the target selection (sorted), or None where
    the selection has too few sources there (a DataError of another kind, e.g. a missing
    instance map, is raised)."""
    try:
        spec = spec_for_frame(seq, frame, selection)
    except TooFewSourcesError:
        return None
    return sorted({int(frame), *(int(f) for f in spec.sources), *(int(f) for f in spec.group)})


def length_view_shift(seq: Sequence, frames: Iterable[int], instance_ids: Iterable[int],
                      probe: float = LENGTH_PROBE_M,
                      cache: dict[int, dict[int, Box3D]] | None = None) -> dict[int, float]:
    """Per car (instance-map values ``instance_ids``), the largest :func:`far_end_shift` of its
    ground-truth box over ``frames`` (0 where none shows it). ``cache`` (frame -> instance id ->
    ground-truth box) may be shared between calls on one sequence."""
    cache = {} if cache is None else cache
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


__all__ = ["labelling_frames", "length_view_shift"]
