"""Frame selection (docs/method.md §5) on hand-built id sets with hand-computed answers."""

from __future__ import annotations

import numpy as np
import pytest

from test_kitti360_loader import SEQ, make_dataset

from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.data.selection import (SelectionConfig, candidate_sources, pick_sources, select_from_ids,
                                    select_targets, spec_for_frame)
from vsrd_mi.errors import DataError

A, B, C, D, E = 26001, 26002, 26003, 26004, 26005


def ids(*values: int) -> frozenset[int]:
    return frozenset(values)


def test_default_window_chunk_middles():
    """100 frames with the same cars: one group, target 50, 16 sources from offsets -25..+24."""
    frame_ids = {f: ids(A, B) for f in range(100)}
    (spec,) = select_from_ids(frame_ids, SelectionConfig())
    assert spec.target == 50 and spec.group == tuple(range(100))
    # candidates: offsets -25..-1, 1..24 (49); chunk sizes 4, 3, ..., 3; middles by hand
    assert spec.candidates == tuple(range(25, 50)) + tuple(range(51, 75))
    offsets = [s - 50 for s in spec.sources]
    assert offsets == [-23, -20, -17, -14, -11, -8, -5, -2, 2, 5, 8, 11, 14, 17, 20, 23]
    assert spec.instance_ids == (A, B) and spec.note is None


def test_small_window_hand_computed():
    cfg = SelectionConfig(num_sources=4, min_sources=2, min_offset=-5, max_offset=4)
    frame_ids = {f: ids(A) for f in range(21)}
    cands = candidate_sources(10, list(range(21)), frame_ids.get, cfg)
    assert cands == [5, 6, 7, 8, 9, 11, 12, 13, 14]
    # chunks [5,6,7] [8,9] [11,12] [13,14] -> middles 6, 9, 12, 14
    assert pick_sources(10, cands, cfg) == ((6, 9, 12, 14), None)


def test_fifty_percent_rule_stops_at_first_failure():
    cfg = SelectionConfig(num_sources=2, min_sources=1)
    frame_ids = {
        10: ids(A, B, C, D),
        11: ids(A, B, C),
        12: ids(A, B, E),        # 2 of 4 = 50 %: still a candidate
        13: ids(A, E),           # 25 %: stop
        14: ids(A, B, C, D),     # never reached
        8: ids(A, B, C, D, E),   # frame 9 has no instance map: skipped, not a failure
        7: ids(C),               # 25 %: stop
        6: ids(A, B, C, D),
    }
    frames = sorted(frame_ids)
    assert candidate_sources(10, frames, frame_ids.get, cfg) == [8, 11, 12]
    # an unreadable map (None) is skipped like a missing one
    frame_ids[11] = None
    assert candidate_sources(10, frames, frame_ids.get, cfg) == [8, 12]


def test_fraction_threshold_is_a_config_field():
    frame_ids = {0: ids(A, B, C, D), 1: ids(A, B), 2: ids(A, B, C)}
    frames = sorted(frame_ids)
    assert candidate_sources(0, frames, frame_ids.get, SelectionConfig(min_id_fraction=0.5)) == [1, 2]
    assert candidate_sources(0, frames, frame_ids.get, SelectionConfig(min_id_fraction=0.6)) == []


def test_groups_are_consecutive_runs_with_identical_ids():
    cfg = SelectionConfig(num_sources=4, min_sources=4)
    frame_ids = {f: ids(A) for f in range(0, 10)}
    frame_ids.update({f: ids(A, B) for f in range(10, 20)})
    frame_ids.update({f: ids(A) for f in range(20, 30)})
    specs = select_from_ids(frame_ids, cfg)
    assert [s.target for s in specs] == [5, 15, 25]
    assert [s.group for s in specs] == [tuple(range(0, 10)), tuple(range(10, 20)), tuple(range(20, 30))]
    assert specs[1].instance_ids == (A, B)
    for s in specs:
        assert s.target not in s.sources and len(s.sources) == 4
        assert list(s.sources) == sorted(s.sources)


def test_target_restriction_keeps_sources_from_whole_sequence():
    cfg = SelectionConfig(num_sources=4, min_sources=4)
    frame_ids = {f: ids(A) for f in range(0, 10)}
    frame_ids.update({f: ids(A, B) for f in range(10, 20)})
    (spec,) = select_from_ids(frame_ids, cfg, targets=range(10, 20))
    assert spec.target == 15 and spec.group == tuple(range(10, 20))
    # {A} holds 50 % of {A, B}: frames before 10 are candidates too
    assert min(spec.candidates) == 0 and min(spec.sources) < 10


def test_even_group_middle_and_empty_frames():
    cfg = SelectionConfig(num_sources=2, min_sources=1)
    frame_ids = {0: ids(A), 1: ids(A), 2: ids(A), 3: ids(A), 4: ids(), 5: ids(A), 6: ids(A)}
    specs = select_from_ids(frame_ids, cfg)
    # frame 4 has no car: it is no target, splits the runs and stops the walks (0 % of the ids);
    # a 4-frame run has its middle at index 2
    assert [(s.target, s.group) for s in specs] == [(2, (0, 1, 2, 3)), (6, (5, 6))]
    assert specs[0].candidates == (0, 1, 3) and specs[0].sources == (1, 3)  # chunks [0, 1] [3]
    assert specs[1].candidates == (5,) and specs[1].sources == (5,) and specs[1].note is not None


def test_short_clip_uses_available_sources_with_note():
    frame_ids = {f: ids(A, B) for f in range(6)}
    (spec,) = select_from_ids(frame_ids, SelectionConfig())
    assert spec.target == 3 and spec.sources == (0, 1, 2, 4, 5)
    assert spec.note is not None and "5 source frames" in spec.note
    assert select_from_ids(frame_ids, SelectionConfig(min_sources=6)) == []


def test_config_validation():
    with pytest.raises(ValueError):
        SelectionConfig(min_id_fraction=0.0)
    with pytest.raises(ValueError):
        SelectionConfig(min_sources=17)
    with pytest.raises(ValueError):
        SelectionConfig(min_offset=1)


def test_select_targets_on_disk_skips_bad_frame(tmp_path, caplog):
    big, small = (20, 20, 59, 59), (100, 40, 104, 44)
    layout = {f: {A: big, B: small} for f in range(9)}
    root = make_dataset(tmp_path, list(range(9)), layout)
    seq = Sequence(root, SEQ)
    cfg = SelectionConfig(num_sources=4, min_sources=4)
    (spec,) = select_targets(seq, cfg)
    assert spec.instance_ids == (A,)  # B is below the size filter
    assert spec.target == 4 and spec.group == tuple(range(9))
    assert spec_for_frame(seq, 4, cfg) == spec

    # damage frame 3's instance map: selection logs it, skips it in walks and splits the group
    path = seq.instance_path(3)
    path.write_bytes(path.read_bytes()[:200])
    seq = Sequence(root, SEQ)
    specs = select_targets(seq, cfg)
    assert "frame 3" in caplog.text
    assert [s.group for s in specs] == [(0, 1, 2), (4, 5, 6, 7, 8)]
    assert all(3 not in s.sources for s in specs)
    with pytest.raises(DataError, match="truncated PNG"):
        seq.instance_map(3)
    # a frame that is no target: no car at all
    with pytest.raises(DataError, match="no instance map"):
        spec_for_frame(seq, 42, cfg)


def test_spec_for_frame_off_middle(tmp_path):
    layout = {f: {A: (20, 20, 59, 59)} for f in range(7)}
    seq = Sequence(make_dataset(tmp_path, list(range(7)), layout), SEQ)
    cfg = SelectionConfig(num_sources=4, min_sources=4)
    spec = spec_for_frame(seq, 1, cfg)
    assert spec.target == 1 and spec.group == tuple(range(7))
    assert spec.candidates == (0, 2, 3, 4, 5, 6)
    assert spec.sources == tuple(int(c[len(c) // 2]) for c in np.array_split([0, 2, 3, 4, 5, 6], 4))
    with pytest.raises(DataError, match="source candidates"):
        spec_for_frame(seq, 1, SelectionConfig(num_sources=8, min_sources=7))
