"""Exact BEV / 3D IoU against analytic values and an independent Monte-Carlo estimate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.iou3d import (bev_footprint, bev_intersection_matrix, bev_iou, bev_iou_matrix,
                                    iou3d, iou3d_matrix, iou_matrices)

W, H, L = 1.8, 1.5, 4.2


def car(x=0.0, y=1.0, z=15.0, yaw=0.0, size=(W, H, L)) -> Box3D:
    return Box3D(centre=(x, y, z), size=size, yaw=yaw)


@pytest.mark.parametrize("yaw", [0.0, 0.3, -1.2, math.pi / 2, 2.9, 7.0])
def test_identical_boxes_have_iou_one(yaw):
    b = car(x=3.7, y=1.2, z=27.3, yaw=yaw)
    assert abs(bev_iou(b, b) - 1.0) < 1e-9
    assert abs(iou3d(b, b) - 1.0) < 1e-9


def test_half_turn_is_the_same_box():
    a, b = car(yaw=0.4), car(yaw=0.4 + math.pi)
    assert abs(iou3d(a, b) - 1.0) < 1e-9


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.0])
@pytest.mark.parametrize("d", [0.1, 1.0, 3.9])
def test_shift_along_length(yaw, d):
    a = car(yaw=yaw)
    shift = d * np.array([math.sin(yaw), 0.0, math.cos(yaw)])  # along the length axis
    b = Box3D(centre=a.centre + shift, size=a.size, yaw=yaw)
    expected = (L - d) / (L + d)
    assert bev_iou(a, b) == pytest.approx(expected, abs=1e-9)
    assert iou3d(a, b) == pytest.approx(expected, abs=1e-9)


@pytest.mark.parametrize("d", [0.2, 1.1])
def test_shift_along_width(d):
    a, b = car(yaw=0.0), car(x=d, yaw=0.0)
    assert bev_iou(a, b) == pytest.approx((W - d) / (W + d), abs=1e-9)


@pytest.mark.parametrize("s", [0.1, 0.75, 1.4])
def test_vertical_shift_changes_3d_but_not_bev(s):
    a, b = car(yaw=0.5), car(y=1.0 + s, yaw=0.5)
    assert bev_iou(a, b) == pytest.approx(1.0, abs=1e-9)
    inter = W * L * (H - s)
    assert iou3d(a, b) == pytest.approx(inter / (2 * W * L * H - inter), abs=1e-9)


def test_diagonal_shift_in_plane_and_height():
    dx, dz, dy = 0.4, 1.3, 0.2
    a, b = car(), car(x=dx, y=1.0 + dy, z=15.0 + dz)
    inter_area = (W - dx) * (L - dz)
    assert bev_iou(a, b) == pytest.approx(inter_area / (2 * W * L - inter_area), abs=1e-9)
    inter = inter_area * (H - dy)
    assert iou3d(a, b) == pytest.approx(inter / (2 * W * L * H - inter), abs=1e-9)


@pytest.mark.parametrize("yaw", [0.0, 0.9])
def test_quarter_turn_about_the_same_centre(yaw):
    a, b = car(yaw=yaw), car(yaw=yaw + math.pi / 2)
    inter = W * W  # the width x width square where the cross overlaps
    assert bev_iou(a, b) == pytest.approx(inter / (2 * W * L - inter), abs=1e-9)
    assert iou3d(a, b) == pytest.approx(inter / (2 * W * L - inter), abs=1e-9)


def test_square_turned_45_degrees_gives_a_regular_octagon():
    s = 2.0
    a, b = car(size=(s, 1.0, s)), car(size=(s, 1.0, s), yaw=math.pi / 4)
    octagon = 2.0 * (math.sqrt(2.0) - 1.0) * s * s
    assert bev_intersection_matrix([a], [b])[0, 0] == pytest.approx(octagon, abs=1e-9)
    assert bev_iou(a, b) == pytest.approx(octagon / (2 * s * s - octagon), abs=1e-9)


@pytest.mark.parametrize("b", [car(x=W + 0.01), car(z=15.0 + L + 1e-6), car(y=1.0 + H + 0.1),
                               car(x=10.0, z=40.0, yaw=1.0)])
def test_disjoint_boxes(b):
    assert iou3d(car(), b) == 0.0


def test_touching_boxes_have_zero_iou():
    assert bev_iou(car(), car(x=W)) == pytest.approx(0.0, abs=1e-12)
    assert iou3d(car(), car(y=1.0 + H)) == pytest.approx(0.0, abs=1e-12)


def test_vertically_disjoint_boxes_still_overlap_in_bev():
    a, b = car(), car(y=1.0 + 2 * H)
    assert bev_iou(a, b) == pytest.approx(1.0, abs=1e-9)
    assert iou3d(a, b) == 0.0


@pytest.mark.parametrize("yaw", [0.0, 0.6])
def test_containment(yaw):
    big = car(yaw=0.2, size=(4.0, 3.0, 8.0))
    small = car(x=0.3, y=1.1, z=15.5, yaw=yaw)  # fits inside for any yaw (its diagonal < 4 m)
    assert iou3d(big, small) == pytest.approx((W * H * L) / (4.0 * 3.0 * 8.0), abs=1e-9)
    assert bev_iou(small, big) == pytest.approx((W * L) / (4.0 * 8.0), abs=1e-9)


def test_matrix_forms_match_pairwise_and_are_symmetric():
    rng = np.random.default_rng(0)
    a = [car(x=rng.uniform(-2, 2), z=rng.uniform(13, 17), yaw=rng.uniform(-3, 3)) for _ in range(4)]
    b = [car(x=rng.uniform(-2, 2), z=rng.uniform(13, 17), yaw=rng.uniform(-3, 3)) for _ in range(3)]
    bev, iou = iou_matrices(a, b)
    assert bev.shape == iou.shape == (4, 3)
    for i in range(4):
        for j in range(3):
            assert bev[i, j] == pytest.approx(bev_iou(a[i], b[j]), abs=1e-12)
            assert iou[i, j] == pytest.approx(iou3d(a[i], b[j]), abs=1e-12)
    np.testing.assert_allclose(bev_iou_matrix(b, a), bev.T, atol=1e-12)
    np.testing.assert_allclose(iou3d_matrix(b, a), iou.T, atol=1e-12)
    assert np.all((iou >= 0) & (iou <= bev + 1e-12))


def test_empty_inputs_give_empty_matrices():
    assert iou3d_matrix([], [car()]).shape == (0, 1)
    assert bev_iou_matrix([car(), car()], []).shape == (2, 0)


def test_footprint_is_the_rotated_rectangle():
    fp = bev_footprint(car(x=1.0, z=10.0, yaw=math.pi / 2))  # length along +x
    assert sorted(np.round(fp[:, 0], 9)) == sorted([1 - L / 2, 1 - L / 2, 1 + L / 2, 1 + L / 2])
    assert sorted(np.round(fp[:, 1], 9)) == sorted([10 - W / 2, 10 - W / 2, 10 + W / 2, 10 + W / 2])


def _inside(points: np.ndarray, box: Box3D) -> np.ndarray:
    """Points inside a box, by rotating into its frame (independent of the implementation)."""
    d = points - box.centre
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    local = np.stack([c * d[:, 0] - s * d[:, 2], d[:, 1], s * d[:, 0] + c * d[:, 2]], axis=1)
    return np.all(np.abs(local) <= 0.5 * box.size, axis=1)


def test_against_monte_carlo():
    rng = np.random.default_rng(12345)
    n = 200_000
    for _ in range(6):
        a = car(x=rng.uniform(-1, 1), y=rng.uniform(0.8, 1.2), z=rng.uniform(14, 16),
                yaw=rng.uniform(-math.pi, math.pi), size=rng.uniform([1.5, 1.2, 3.0], [2.2, 1.9, 5.5]))
        b = car(x=rng.uniform(-1, 1), y=rng.uniform(0.8, 1.2), z=rng.uniform(14, 16),
                yaw=rng.uniform(-math.pi, math.pi), size=rng.uniform([1.5, 1.2, 3.0], [2.2, 1.9, 5.5]))
        corners = np.concatenate([a.corners(), b.corners()])
        pts = rng.uniform(corners.min(axis=0), corners.max(axis=0), size=(n, 3))
        in_a, in_b = _inside(pts, a), _inside(pts, b)
        n_union = np.count_nonzero(in_a | in_b)
        p = np.count_nonzero(in_a & in_b) / n_union
        sigma = math.sqrt(p * (1 - p) / n_union)
        exact = iou3d(a, b)
        assert 0.0 < exact < 1.0
        assert abs(exact - p) < 3 * sigma + 1e-9, (exact, p, sigma)


def test_identity_symmetry_and_bounds_on_random_boxes():
    rng = np.random.default_rng(7)
    for _ in range(200):
        a, b = (car(x=rng.uniform(-100, 100), y=rng.uniform(-2, 3), z=rng.uniform(0.5, 100),
                    yaw=rng.uniform(-10, 10), size=rng.uniform(0.1, 6.0, 3)) for _ in range(2))
        b = Box3D(centre=a.centre + rng.normal(0, 1.0, 3), size=b.size, yaw=b.yaw)
        assert abs(iou3d(a, a) - 1.0) < 1e-9 and abs(bev_iou(a, a) - 1.0) < 1e-9
        bev_ab, iou_ab = iou_matrices([a], [b])
        bev_ba, iou_ba = iou_matrices([b], [a])
        assert bev_ab[0, 0] == pytest.approx(bev_ba[0, 0], abs=1e-12)
        assert iou_ab[0, 0] == pytest.approx(iou_ba[0, 0], abs=1e-12)
        assert 0.0 <= iou_ab[0, 0] <= bev_ab[0, 0] + 1e-12 <= 1.0 + 2e-12
