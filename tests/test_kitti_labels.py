"""KITTI label files: parsing, formatting, atomic writing and Box3D conversion."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from vsrd_mi.data.kitti_labels import (
    DEFAULT_DECIMALS,
    KittiLabel,
    box_from_label,
    format_label_line,
    label_from_box,
    parse_label_line,
    read_labels,
    write_labels,
)
from vsrd_mi.errors import DataError
from vsrd_mi.geometry.boxes import Box3D, wrap_angle

# A line from the KITTI object benchmark's training labels (000000.txt is a pedestrian; this is a car).
KITTI_CAR = "Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59"


def test_parse_a_kitti_line():
    lab = parse_label_line(KITTI_CAR)
    assert lab.type == "Car" and lab.truncated == 0.0 and lab.occluded == 0
    assert lab.alpha == -1.58 and lab.box2d == (587.01, 173.33, 614.12, 200.12)
    assert (lab.h, lab.w, lab.l) == (1.65, 1.67, 3.64)
    assert (lab.x, lab.y, lab.z, lab.ry) == (-0.65, 1.71, 46.70, -1.59)
    assert lab.score is None
    assert lab.height_2d == pytest.approx(200.12 - 173.33)
    assert parse_label_line(KITTI_CAR + " 0.87").score == 0.87


def test_box_from_label_uses_bottom_centre_and_ry():
    box = box_from_label(parse_label_line(KITTI_CAR))
    np.testing.assert_allclose(box.centre, [-0.65, 1.71 - 1.65 / 2, 46.70])
    np.testing.assert_allclose(box.size, [1.67, 1.65, 3.64])
    assert box.yaw == pytest.approx(-1.59 + math.pi / 2)
    # KITTI's heading (its local +x turned by R_y(ry)) is (cos ry, 0, -sin ry); our length axis
    # (sin yaw, 0, cos yaw) must be the same direction.
    ry = -1.59
    heading_kitti = np.array([math.cos(ry), 0.0, -math.sin(ry)])
    assert heading_kitti @ box.heading == pytest.approx(1.0, abs=1e-12)


def test_label_from_box_fields():
    box = Box3D(centre=(2.0, 0.9, 20.0), size=(1.8, 1.5, 4.4), yaw=0.3)
    lab = label_from_box(box, (10.0, 20.0, 110.0, 80.0), score=0.75)
    assert (lab.w, lab.h, lab.l) == (1.8, 1.5, 4.4)
    assert (lab.x, lab.y, lab.z) == pytest.approx((2.0, 0.9 + 0.75, 20.0))
    assert lab.ry == pytest.approx(0.3 - math.pi / 2)
    assert lab.alpha == pytest.approx(0.3 - math.pi / 2 - math.atan2(2.0, 20.0))
    assert lab.type == "Car" and lab.score == 0.75 and lab.box2d == (10.0, 20.0, 110.0, 80.0)


@pytest.mark.parametrize("seed", range(5))
def test_round_trip_box_label_text_box(seed):
    rng = np.random.default_rng(seed)
    tol = 0.5 * 10.0 ** -DEFAULT_DECIMALS + 1e-12
    for _ in range(50):
        box = Box3D(centre=rng.uniform([-30, -1, 1], [30, 3, 80]),
                    size=rng.uniform([1.4, 1.1, 3.0], [2.4, 2.2, 6.0]),
                    yaw=rng.uniform(-math.pi, math.pi))
        text = format_label_line(label_from_box(box, rng.uniform(0, 300, 4), score=rng.uniform()))
        back = box_from_label(parse_label_line(text))
        np.testing.assert_allclose(back.size, box.size, atol=tol, rtol=0)
        # the centre's y is bottom y - h/2: two rounded numbers
        np.testing.assert_allclose(back.centre, box.centre, atol=2 * tol, rtol=0)
        assert abs(wrap_angle(back.yaw - box.yaw)) <= tol


def test_write_and_read_back(tmp_path):
    labels = [parse_label_line(KITTI_CAR + " 0.5"),
              parse_label_line("DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10")]
    path = tmp_path / "sub" / "0000000042.txt"
    write_labels(path, labels)
    assert read_labels(path) == labels
    assert oct(os.stat(path).st_mode & 0o777) == oct(0o644)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temp file left behind
    write_labels(path, [])
    assert read_labels(path) == [] and path.read_text() == ""


def test_write_is_atomic_on_failure(tmp_path):
    path = tmp_path / "labels.txt"
    write_labels(path, [parse_label_line(KITTI_CAR)])
    bad = KittiLabel("Car", 0.0, 0, 0.0, (0, 0, 1, 1), 1.5, 1.8, 4.0, 0.0, 1.0, 10.0, math.nan, 0.5)
    with pytest.raises(ValueError, match="non-finite"):
        write_labels(path, [parse_label_line(KITTI_CAR), bad])
    assert read_labels(path) == [parse_label_line(KITTI_CAR)]
    assert [p.name for p in tmp_path.iterdir()] == ["labels.txt"]


def test_blank_lines_are_skipped(tmp_path):
    path = tmp_path / "x.txt"
    path.write_text("\n" + KITTI_CAR + "\n\n   \n" + KITTI_CAR + " 0.1\n")
    assert len(read_labels(path)) == 2


@pytest.mark.parametrize("line, problem", [
    ("Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70", "got 14"),
    (KITTI_CAR + " 0.5 0.6", "got 17"),
    (KITTI_CAR.replace("46.70", "abc"), "not a number"),
    (KITTI_CAR.replace("46.70", "nan"), "non-finite"),
    (KITTI_CAR.replace("1.67", "inf"), "non-finite"),
    (KITTI_CAR.replace(" 0 -1.58", " 0.5 -1.58"), "occluded"),
])
def test_malformed_lines_name_file_and_line(tmp_path, line, problem):
    path = tmp_path / "bad.txt"
    path.write_text(KITTI_CAR + "\n" + line + "\n")
    with pytest.raises(DataError, match=problem) as info:
        read_labels(path)
    assert str(path) in str(info.value) and "line 2" in str(info.value)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(DataError, match="not found"):
        read_labels(tmp_path / "nope.txt")
    (tmp_path / "bin.txt").write_bytes(b"Car \xff\xfe 0 0")
    with pytest.raises(DataError, match="non-ASCII"):
        read_labels(tmp_path / "bin.txt")
    with pytest.raises(DataError, match="directory"):
        read_labels(tmp_path)


def test_format_rejects_bad_type():
    lab = parse_label_line(KITTI_CAR)
    with pytest.raises(ValueError, match="type"):
        format_label_line(KittiLabel("Big Car", *list(lab.__dict__.values())[1:]))


def test_dontcare_is_not_a_box():
    lab = parse_label_line("DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10")
    with pytest.raises(ValueError):
        box_from_label(lab)
