"""Every bad input gives one clear DataError naming the file and the problem."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_kitti360_loader import SEQ, H, W, make_dataset

from vsrd_mi.batch import atomic
from vsrd_mi.data import kitti360_write as kw
from vsrd_mi.data.kitti360 import (
    CAR_KITTI_ID,
    Sequence,
    read_calibration,
    read_cam0_to_world,
    read_world_boxes,
)
from vsrd_mi.data.kitti_labels import parse_label_line, write_labels
from vsrd_mi.data.observations import load_observations
from vsrd_mi.data.selection import SelectionConfig, select_targets, spec_for_frame
from vsrd_mi.errors import DataError

FRAMES = [0, 1, 2, 3]


@pytest.fixture
def root(tmp_path: Path) -> Path:
    layout = {f: {26001: (10, 10, 40, 40)} for f in FRAMES}
    box = kw.world_box(1, CAR_KITTI_ID, (10, 0, 0.7), (4, 2, 1.5), 0.0, 0, 3)
    return make_dataset(tmp_path / "kitti", FRAMES, layout, world_boxes=[box])


def expect(path: Path, match: str):
    """pytest.raises(DataError) whose message names ``path`` and matches ``match``."""
    class _Ctx:
        def __enter__(self):
            self.ctx = pytest.raises(DataError, match=match)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            out = self.ctx.__exit__(*exc)
            assert str(path) in str(self.info.value), str(self.info.value)
            assert self.info.value.path == str(path)
            return out
    return _Ctx()


def pose_file(root: Path) -> Path:
    return root / "data_poses" / SEQ / "cam0_to_world.txt"


def edit_line(path: Path, index: int, fn) -> None:
    lines = path.read_text().splitlines()
    lines[index] = fn(lines[index])
    path.write_text("\n".join(lines) + "\n")


# -- images -------------------------------------------------------------------------------------


def test_truncated_png(root):
    seq = Sequence(root, SEQ)
    path = seq.image_path(1)
    path.write_bytes(path.read_bytes()[:-40])
    with expect(path, "truncated PNG"):
        seq.image(1)
    inst = seq.instance_path(2)
    inst.write_bytes(inst.read_bytes()[: len(inst.read_bytes()) // 2])
    with expect(inst, "truncated PNG"):
        seq.instance_map(2)


def test_corrupt_png_and_not_png(root):
    seq = Sequence(root, SEQ)
    path = seq.image_path(1)
    data = bytearray(path.read_bytes())
    data[60] ^= 0xFF  # inside the first data chunk
    path.write_bytes(bytes(data))
    with expect(path, "CRC mismatch"):
        seq.image(1)
    path.write_text("hello")
    with expect(path, "not a PNG"):
        seq.image(1)


def test_eight_bit_instance_png(root):
    seq = Sequence(root, SEQ)
    path = seq.instance_path(0)
    cv2.imwrite(str(path), np.zeros((H, W), dtype=np.uint8))
    with expect(path, "8-bit, expected 16-bit"):
        seq.instance_map(0)


def test_sixteen_bit_rgb_image(root):
    seq = Sequence(root, SEQ)
    path = seq.image_path(0, camera=1)
    cv2.imwrite(str(path), np.zeros((H, W, 3), dtype=np.uint16))
    with expect(path, "16-bit, expected 8-bit"):
        seq.image(0, camera=1)


def test_image_of_wrong_size(root):
    seq = Sequence(root, SEQ)
    path = seq.image_path(2)
    cv2.imwrite(str(path), np.zeros((H, W + 1, 3), dtype=np.uint8))
    with expect(path, f"{W + 1}x{H} pixels, expected {W}x{H}"):
        seq.image(2)
    inst = seq.instance_path(2)
    cv2.imwrite(str(inst), np.zeros((H - 2, W), dtype=np.uint16))
    with expect(inst, "expected"):
        seq.instance_map(2)


def test_missing_instance_map_of_listed_frame(root):
    seq = Sequence(root, SEQ)
    path = seq.instance_path(3)
    path.unlink()
    with expect(path, "missing instance map"):
        seq.instance_map(3)


# -- calibration --------------------------------------------------------------------------------


def test_missing_calibration_key(root):
    path = root / "calibration" / "perspective.txt"
    path.write_text("\n".join(l for l in path.read_text().splitlines() if not l.startswith("P_rect_01")))
    with expect(path, "missing key 'P_rect_01'"):
        read_calibration(root)
    with expect(path, "missing key"):
        Sequence(root, SEQ)


def test_calibration_wrong_count_and_not_a_number(root):
    path = root / "calibration" / "perspective.txt"
    original = path.read_text()
    path.write_text(original.replace("R_rect_00: ", "R_rect_00: 1.0 "))
    with expect(path, "'R_rect_00' has 10 values, expected 9"):
        read_calibration(root)
    path.write_text(original.replace("S_rect_00: ", "S_rect_00: x"))
    with expect(path, "line 1: not a number"):
        read_calibration(root)
    path.write_text(original + "garbage line\n")
    with expect(path, "expected 'KEY: values'"):
        read_calibration(root)
    path.unlink()
    with expect(path, "missing calibration file"):
        read_calibration(root)


# -- poses --------------------------------------------------------------------------------------


def test_pose_line_with_15_numbers(root):
    path = pose_file(root)
    edit_line(path, 2, lambda l: l.rsplit(" ", 1)[0])
    with expect(path, "line 3: 15 numbers after the frame index, expected 16"):
        Sequence(root, SEQ)


def test_duplicate_pose_lines(root):
    path = pose_file(root)
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines + [lines[1]]) + "\n")
    with expect(path, "line 5: duplicate pose for frame 1"):
        read_cam0_to_world(root, SEQ)


def test_non_finite_pose(root):
    path = pose_file(root)
    edit_line(path, 1, lambda l: l.replace(l.split()[4], "nan", 1))
    with expect(path, "line 2: non-finite value"):
        Sequence(root, SEQ)
    edit_line(path, 1, lambda l: l.replace("nan", "inf"))
    with expect(path, "line 2: non-finite"):
        Sequence(root, SEQ)


def test_bad_frame_index(root):
    path = pose_file(root)
    edit_line(path, 0, lambda l: "-1" + l[1:])
    with expect(path, "line 1: bad frame index"):
        Sequence(root, SEQ)


def test_frame_without_pose_not_listed_and_error_when_asked(root):
    path = pose_file(root)
    lines = path.read_text().splitlines()
    path.write_text("\n".join(l for l in lines if not l.startswith("2 ")) + "\n")
    seq = Sequence(root, SEQ)
    assert seq.frames == [0, 1, 3]
    assert seq.mask_frames == [0, 1, 3]
    pdir = root / "data_poses" / SEQ
    with expect(pdir, "no pose for frame 2"):
        seq.cam0_to_world(2)
    with expect(pdir, "no pose for frame 2"):
        seq.image(2)


def test_imu_poses_without_cam_to_pose_calibration(root):
    shutil.move(pose_file(root), root / "data_poses" / SEQ / "poses.txt")
    path = root / "data_poses" / SEQ / "poses.txt"
    path.write_text("".join(" ".join(l.split()[:13]) + "\n" for l in path.read_text().splitlines()))
    with expect(root / "calibration" / "calib_cam_to_pose.txt", "needed to convert"):
        Sequence(root, SEQ)


def test_missing_pose_files(root):
    pose_file(root).unlink()
    with expect(root / "data_poses" / SEQ, "missing pose files"):
        Sequence(root, SEQ)


# -- directories --------------------------------------------------------------------------------


def test_missing_directory(tmp_path, root):
    with expect(tmp_path / "nowhere", "missing dataset directory"):
        Sequence(tmp_path / "nowhere", SEQ)
    other = "2013_05_28_drive_0009_sync"
    with expect(root / "data_poses" / other, "missing pose files"):
        Sequence(root, other)
    shutil.rmtree(root / "data_2d_raw" / SEQ / "image_00")
    with expect(root / "data_2d_raw" / SEQ / "image_00" / "data_rect", "missing image directory"):
        Sequence(root, SEQ)


# -- 3D boxes -----------------------------------------------------------------------------------


def test_malformed_xml(root):
    seq = Sequence(root, SEQ)
    path = seq.boxes_path
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with expect(path, "malformed XML"):
        seq.ground_truth(0)


def test_xml_missing_field_and_bad_matrix(root):
    path = Sequence(root, SEQ).boxes_path
    text = path.read_text()
    path.write_text(text.replace("<instanceId>1</instanceId>", ""))
    with expect(path, "has no <instanceId>"):
        read_world_boxes(path)
    path.write_text(text.replace("<timestamp>-1</timestamp>", "<timestamp>soon</timestamp>"))
    with expect(path, "<timestamp> is not an integer"):
        read_world_boxes(path)
    data_start = text.index("<data>", text.index("<transform"))
    path.write_text(text[:data_start + 6] + "1.0 " + text[data_start + 6:])
    with expect(path, "transform> has 17 values, expected 4x4"):
        read_world_boxes(path)
    path.write_text(text[:data_start + 6] + "nan " + text[data_start + 10:])
    with expect(path, "non-finite"):
        read_world_boxes(path)
    path.unlink()
    with expect(path, "missing 3D box file"):
        read_world_boxes(path)


# -- a sequence with some bad frames ------------------------------------------------------------


def test_good_frames_survive_bad_ones(root):
    seq = Sequence(root, SEQ)
    seq.image_path(1).write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 10)
    cv2.imwrite(str(seq.instance_path(2)), np.zeros((H, W), dtype=np.uint8))
    seq = Sequence(root, SEQ)
    assert seq.frames == FRAMES  # listing never opens the files
    for f in (0, 3):
        assert seq.image(f).shape == (H, W, 3)
        assert list(seq.car_instances(f)) == [26001]
    assert seq.instance_map(1).shape == (H, W)
    with pytest.raises(DataError):
        seq.image(1)
    with pytest.raises(DataError):
        seq.car_instances(2)
    assert len(seq.ground_truth(3)) == 1


# -- masks: no car anywhere, a car seen only in the target -----------------------------------------

#: Selection for the 9-frame toy sequences below (the default needs 16 / at least 4 sources).
SMALL_SELECTION = SelectionConfig(num_sources=4, min_sources=4)
NINE = list(range(9))
A, C = 26001, 26003


def test_empty_masks_everywhere(tmp_path, capsys):
    seq = Sequence(make_dataset(tmp_path / "kitti", NINE, {f: {} for f in NINE}), SEQ)
    assert select_targets(seq, SMALL_SELECTION) == []  # nothing to label is not a crash
    with expect(seq.instance_path(4), "frame 4 has no car passing the size filter"):
        spec_for_frame(seq, 4, SMALL_SELECTION)
    # the CLI says so, naming the instance-map directory, and fails (nothing written)
    from vsrd_mi.cli import main
    assert main(["autolabel", str(tmp_path / "kitti"), "--sequence", SEQ, "--out",
                 str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert str(seq.instance_dir) in err and "no target frame" in err and "nothing to label" in err
    assert not (tmp_path / "out").exists()


def test_instance_present_only_in_the_target(tmp_path):
    layout = {f: {} for f in NINE}
    layout[4] = {C: (10, 10, 40, 40)}
    seq = Sequence(make_dataset(tmp_path / "alone", NINE, layout), SEQ)
    assert select_targets(seq, SMALL_SELECTION) == []
    with expect(seq.instance_path(4), "frame 4 has only 0 source candidates \\(need 4\\)"):
        spec_for_frame(seq, 4, SMALL_SELECTION)
    # beside a car seen in every frame it stays a target instance, supervised by the target only
    layout = {f: {A: (60, 20, 99, 59)} for f in NINE}
    layout[4][C] = (10, 10, 40, 40)
    seq = Sequence(make_dataset(tmp_path / "beside", NINE, layout), SEQ)
    spec = spec_for_frame(seq, 4, SMALL_SELECTION)
    assert spec.instance_ids == (A, C) and spec.group == (4,) and len(spec.sources) == 4
    obs = load_observations(seq, spec)
    c = list(obs.instance_ids).index(C)
    assert obs.visible[0, c] and not obs.visible[1:, c].any()
    assert np.isnan(obs.boxes2d[1:, c]).all() and not obs.masks[1:, c].any()


# -- unreadable directories ---------------------------------------------------------------------


def deny_listing(monkeypatch, directory: Path) -> None:
    """Make ``directory`` unreadable: mode 000 (enough for a normal user) and, since root reads
    anything, listing it raises ``PermissionError`` like the kernel would (the caller restores
    the mode)."""
    directory.chmod(0)
    real_listdir, real_scandir = os.listdir, os.scandir

    def refuse(path):
        if Path(os.fsdecode(path)) == directory:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(directory))

    monkeypatch.setattr(os, "listdir", lambda path=".": refuse(path) or real_listdir(path))
    monkeypatch.setattr(os, "scandir", lambda path=".": refuse(path) or real_scandir(path))


@pytest.fixture
def unreadable(monkeypatch):
    denied = []

    def deny(directory: Path) -> None:
        denied.append((directory, directory.stat().st_mode))
        deny_listing(monkeypatch, directory)

    yield deny
    for directory, mode in denied:
        directory.chmod(mode)


def test_unreadable_image_directory(root, unreadable):
    directory = root / "data_2d_raw" / SEQ / "image_00" / "data_rect"
    unreadable(directory)
    with expect(directory, "cannot list directory"):
        Sequence(root, SEQ)


def test_unreadable_instance_directory(root, unreadable):
    seq = Sequence(root, SEQ)
    unreadable(seq.instance_dir)
    with expect(seq.instance_dir, "cannot list directory"):
        seq.mask_frames  # noqa: B018  (the property lists the directory)


# -- disk full on output ------------------------------------------------------------------------


class FullDisk:
    """A file object whose writes fail with ENOSPC (everything else is the real file)."""

    def __init__(self, f):
        self._f = f

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()
        return False

    def __getattr__(self, name):
        return getattr(self._f, name)


def fill_disk(monkeypatch) -> None:
    real_fdopen = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda *a, **kw: FullDisk(real_fdopen(*a, **kw)))


@pytest.mark.parametrize("writer", ["json", "text", "labels"])
def test_disk_full_on_output(tmp_path, monkeypatch, writer):
    label = parse_label_line("Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59")
    write = {"json": lambda p: atomic.atomic_write_json(p, {"boxes": [1, 2, 3]}),
             "text": lambda p: atomic.atomic_write_text(p, "new\n"),
             "labels": lambda p: write_labels(p, [label, label])}[writer]
    path = tmp_path / "out" / ("0000000014.json" if writer == "json" else "0000000014.txt")
    path.parent.mkdir()
    path.write_bytes(b"the previous, complete output\n")
    fill_disk(monkeypatch)
    with pytest.raises(OSError) as info:
        write(path)
    assert info.value.errno == errno.ENOSPC
    assert str(path) in str(info.value) and "No space left on device" in str(info.value)
    monkeypatch.undo()
    assert path.read_bytes() == b"the previous, complete output\n"
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left
