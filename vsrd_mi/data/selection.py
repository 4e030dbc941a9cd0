"""Which frames to optimise and which source frames supervise them (docs/method.md §5).

For a candidate target frame ``t`` with target ids ``I_t`` (cars passing the size filter):

1. walk forward frame by frame, then backward, over the frames that have instance maps, while at
   least ``min_id_fraction`` of ``I_t`` is present (same filter) and stop at the first failure;
   frames without an instance map are skipped, not treated as failures (as the reference does);
2. keep the candidates with offsets in ``[min_offset, max_offset]``;
3. with at least ``num_sources`` candidates, split them (sorted) into ``num_sources`` chunks and take
   the middle of each; with fewer but at least ``min_sources``, use them all and say so in
   :attr:`TargetSpec.note`; with fewer still, the frame is no target.

Frames qualifying as targets with the identical id set form a *group*; only the middle frame of a
group is optimised and its boxes are shared with the group. Groups here are maximal runs of
*consecutive* qualifying frames (the reference pools all frames of a sequence with the same id set,
even far apart; sharing boxes across a gap would extrapolate velocities over it, so a gap starts a
new group here).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Iterable, Mapping

import numpy as np

from ..errors import DataError
from .kitti360 import Sequence
from .masks import valid_car_ids

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SelectionConfig:
    """Frame-selection thresholds (defaults: the authors' code, docs/method.md §5)."""

    #: Smallest car mask (pixels) that counts as a target instance.
    min_mask_area: int = 128
    #: Smallest side (pixels) of the tight 2D box of a target instance's mask.
    min_box_side: float = 16.0
    #: Fraction of the target ids a frame must show to stay a source candidate.
    min_id_fraction: float = 0.5
    #: Number of source frames per target (chunks of the candidate window).
    num_sources: int = 16
    #: Earliest source offset (frames relative to the target) kept from the candidate window.
    min_offset: int = -25
    #: Latest source offset kept from the candidate window.
    max_offset: int = 24
    #: Fewest sources with which a target is still optimised (short clips use every candidate down
    #: to this number; three views beside the target are too few to pin down depth and length).
    min_sources: int = 4

    def __post_init__(self) -> None:
        if not 0.0 < self.min_id_fraction <= 1.0:
            raise ValueError(f"min_id_fraction must be in (0, 1], got {self.min_id_fraction}")
        if not 1 <= self.min_sources <= self.num_sources:
            raise ValueError(f"need 1 <= min_sources <= num_sources, got {self.min_sources}, {self.num_sources}")
        if self.min_offset >= 0 or self.max_offset <= 0:
            raise ValueError(f"need min_offset < 0 < max_offset, got {self.min_offset}, {self.max_offset}")


@dataclass(frozen=True)
class TargetSpec:
    """One frame to optimise: its sources, its group and its target instances."""

    #: The target frame index.
    target: int
    #: Source frame indices, sorted (never containing the target).
    sources: tuple[int, ...]
    #: Frames sharing the target's id set (consecutive run; the target is its middle), sorted.
    group: tuple[int, ...]
    #: Target instance values (26001..26999), sorted.
    instance_ids: tuple[int, ...]
    #: All source candidates found by the walk (after the offset cap), sorted.
    candidates: tuple[int, ...] = ()
    #: Set when fewer than ``num_sources`` sources were available (short clip), else None.
    note: str | None = None


IdLookup = Callable[[int], "frozenset[int] | None"]


def candidate_sources(frame: int, frames: list[int], ids: IdLookup, cfg: SelectionConfig) -> list[int]:
    """Source candidates of ``frame`` (step 1 and 2 of the module doc), sorted.

    ``frames`` are the sorted frames with instance maps; ``ids(f)`` gives the valid id set of
    frame ``f`` or None when it cannot be read (skipped like a missing frame).
    """
    target_ids = ids(frame)
    if not target_ids:
        return []
    pos = frames.index(frame)
    need = cfg.min_id_fraction * len(target_ids)
    out = []
    for step in (1, -1):
        i = pos + step
        # frames beyond the offset cap are never kept, so the walk stops there (same result)
        while 0 <= i < len(frames) and cfg.min_offset <= frames[i] - frame <= cfg.max_offset:
            f_ids = ids(frames[i])
            if f_ids is not None:
                if len(target_ids & f_ids) < need:
                    break
                out.append(frames[i])
            i += step
    return sorted(out)


def pick_sources(frame: int, candidates: list[int], cfg: SelectionConfig) -> tuple[tuple[int, ...], str | None] | None:
    """Chunk-middle sources from sorted ``candidates`` (step 3); None if too few."""
    n = len(candidates)
    if n < cfg.min_sources:
        return None
    if n < cfg.num_sources:
        return tuple(candidates), (f"frame {frame}: only {n} source frames available "
                                   f"(fewer than {cfg.num_sources}); using all of them")
    chunks = np.array_split(np.asarray(candidates), cfg.num_sources)
    return tuple(int(c[len(c) // 2]) for c in chunks), None


def select_from_ids(frame_ids: Mapping[int, frozenset[int] | None], cfg: SelectionConfig,
                    targets: Iterable[int] | None = None) -> list[TargetSpec]:
    """Target specs from per-frame valid id sets (the pure core of :func:`select_targets`).

    ``frame_ids`` maps every frame with an instance map to its valid car ids (None: unreadable).
    ``targets`` limits which frames may be targets; sources still come from all frames.
    """
    frames = sorted(frame_ids)
    allowed = set(frames) if targets is None else set(targets) & set(frames)
    lookup = frame_ids.get
    qualified: dict[int, tuple[tuple[int, ...], str | None, tuple[int, ...]]] = {}
    for f in frames:
        if f not in allowed or not frame_ids[f]:
            continue
        cands = candidate_sources(f, frames, lookup, cfg)
        picked = pick_sources(f, cands, cfg)
        if picked is not None:
            qualified[f] = (picked[0], picked[1], tuple(cands))
    specs = []
    run: list[int] = []

    def close_run() -> None:
        if run:
            mid = run[len(run) // 2]
            sources, note, cands = qualified[mid]
            specs.append(TargetSpec(target=mid, sources=sources, group=tuple(run),
                                    instance_ids=tuple(sorted(frame_ids[mid])),
                                    candidates=cands, note=note))
            run.clear()

    prev_index = None
    for index, f in enumerate(frames):
        if f not in qualified:
            close_run()
            continue
        if run and (prev_index != index - 1 or frame_ids[f] != frame_ids[run[-1]]):
            close_run()
        run.append(f)
        prev_index = index
    close_run()
    return specs


class FrameIds:
    """Lazily read, cached valid car ids per frame of a sequence (callable: frame -> ids or None).

    A damaged instance map is logged and yields None, which the selection treats like a missing
    map, so the rest of the sequence stays usable (reading that frame directly still raises its
    :class:`DataError`).
    """

    def __init__(self, seq: Sequence, cfg: SelectionConfig):
        self.seq, self.cfg = seq, cfg
        self._cache: dict[int, frozenset[int] | None] = {}

    def __call__(self, frame: int) -> frozenset[int] | None:
        if frame not in self._cache:
            try:
                ids: frozenset[int] | None = valid_car_ids(
                    self.seq.instance_map(frame), self.cfg.min_mask_area, self.cfg.min_box_side)
            except DataError as exc:
                log.warning("skipping frame %d: %s", frame, exc)
                ids = None
            self._cache[frame] = ids
        return self._cache[frame]


def frame_id_sets(seq: Sequence, cfg: SelectionConfig) -> dict[int, frozenset[int] | None]:
    """Valid car ids of every frame of ``seq`` with an instance map (None: unreadable, see :class:`FrameIds`)."""
    ids = FrameIds(seq, cfg)
    return {f: ids(f) for f in seq.mask_frames}


def select_targets(seq: Sequence, cfg: SelectionConfig | None = None,
                   frames: Iterable[int] | None = None) -> list[TargetSpec]:
    """Frames of ``seq`` to optimise, one :class:`TargetSpec` per group (docs/method.md §5).

    ``frames`` limits which frames may be targets; sources come from the whole sequence.
    """
    cfg = cfg or SelectionConfig()
    if not seq.has_masks:
        raise DataError(seq.instance_dir, "missing instance-map directory (frame selection needs masks)")
    return select_from_ids(frame_id_sets(seq, cfg), cfg, frames)


class TooFewSourcesError(DataError):
    """A frame the selection cannot make a target of: fewer source candidates than
    ``SelectionConfig.min_sources`` (the frame and its masks are fine otherwise)."""


def spec_for_frame(seq: Sequence, frame: int, cfg: SelectionConfig | None = None) -> TargetSpec:
    """The :class:`TargetSpec` with ``frame`` itself as target (whether or not it is a group middle).

    Reads only the instance maps the walks reach. Its group is the run of consecutive qualifying
    frames with its id set, as in :func:`select_targets`. Raises DataError when the frame has no
    usable instance map, no target instance or (:class:`TooFewSourcesError`) too few sources.
    """
    cfg = cfg or SelectionConfig()
    frames = seq.mask_frames
    if frame not in frames:
        raise DataError(seq.instance_path(frame), f"frame {frame} has no instance map (or no pose/image)")
    target_ids = valid_car_ids(seq.instance_map(frame), cfg.min_mask_area, cfg.min_box_side)
    if not target_ids:
        raise DataError(seq.instance_path(frame), f"frame {frame} has no car passing the size filter")
    ids = FrameIds(seq, cfg)
    cands = candidate_sources(frame, frames, ids, cfg)
    picked = pick_sources(frame, cands, cfg)
    if picked is None:
        raise TooFewSourcesError(seq.instance_path(frame), f"frame {frame} has only {len(cands)} source "
                                                           f"candidates (need {cfg.min_sources})")

    def same_group(f: int) -> bool:
        return ids(f) == target_ids and pick_sources(f, candidate_sources(f, frames, ids, cfg), cfg) is not None

    pos = frames.index(frame)
    lo, hi = pos, pos
    while lo > 0 and same_group(frames[lo - 1]):
        lo -= 1
    while hi + 1 < len(frames) and same_group(frames[hi + 1]):
        hi += 1
    return TargetSpec(target=frame, sources=picked[0], group=tuple(frames[lo:hi + 1]),
                      instance_ids=tuple(sorted(target_ids)), candidates=tuple(cands), note=picked[1])
