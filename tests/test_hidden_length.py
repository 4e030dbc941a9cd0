"""Lengths held from inside only (vsrd_mi.optimise.hidden_length): the truncated-normal mean
against numerical integration, end moves against exact geometry, and the end test on a car whose
far end an occluder hides, through the projection loss."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm, truncnorm

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant)
from vsrd_plugins.sdf import InstanceField
from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.vehicle_sizes import length_given_height
from vsrd_mi.optimise import losses
from vsrd_mi.optimise.losses import to_float
from vsrd_mi.optimise.config import CarProfile, HiddenLengthConfig, LossWeights
from vsrd_mi.optimise.hidden_length import (
    EndCosts, LaneLoss, estimate_hidden_lengths, expected_length, free_ends, free_travel, held_from_inside, moved_end,
    move_ends, projection_box_loss)

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
IMAGE_BOUNDS = np.array([-0.5, -0.5, 1279.5, 479.5])
PROFILE = CarProfile(clearance=0.25, overhang=0.2, corner=0.3, fit_corner=False, mirror=0.0, roof=1.0)
#: Both steps: ends held from inside, and lengths no view measures (off by default).
CFG = HiddenLengthConfig(unmeasured=True)
#: The ends held from inside alone (the default: lengths no view measures left as they are).
HELD_ONLY = HiddenLengthConfig()


@pytest.mark.parametrize("lower, height", [(3.0, 1.5), (4.5, 1.45), (4.76, 1.9), (6.5, 1.5), (9.0, 1.5)])
def test_expected_length_is_the_truncated_normal_mean(lower, height):
    a, b, sd = length_given_height()
    mu = a + b * height
    want = truncnorm.mean((lower - mu) / sd, np.inf, loc=mu, scale=sd)
    if np.isfinite(want):
        num, _ = quad(lambda x: x * norm.pdf(x, mu, sd), lower, np.inf)
        mass = norm.sf(lower, mu, sd)
        if mass > 1e-9:  # quadrature agrees where the tail holds any mass
            assert num / mass == pytest.approx(want, abs=1e-4)
    got = expected_length(np.array([lower]), np.array([height]))[0]
    assert got == pytest.approx(want, abs=1e-6)
    assert got > lower


def test_expected_length_grows_with_height_and_the_bound():
    e = expected_length(np.array([4.0, 4.0, 5.0]), np.array([1.5, 1.9, 1.9]))
    assert e[0] < e[1] < e[2]
    with pytest.raises(ValueError, match="spread"):
        expected_length(np.array([4.0]), np.array([1.5]), prior=(2.7, 1.2, 0.0))


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.3])
def test_moved_end_keeps_the_other_face(yaw):
    centre, size = np.array([[1.0, 0.8, 12.0]]), np.array([[1.8, 1.5, 4.2]])
    axis = np.array([np.sin(yaw), 0.0, np.cos(yaw)])
    for end, sign in ((0, 1.0), (1, -1.0)):
        c, s = moved_end(centre, size, np.array([yaw]), end, np.array([0.5]))
        assert s[0, 2] == pytest.approx(4.7)
        # the moved face went out by 0.5 m, the other stayed
        assert c[0] + sign * 0.5 * s[0, 2] * axis == pytest.approx(centre[0] + sign * (2.1 + 0.5) * axis)
        assert c[0] - sign * 0.5 * s[0, 2] * axis == pytest.approx(centre[0] - sign * 2.1 * axis)


def test_held_from_inside_needs_a_cost_inwards_in_few_views_and_none_outwards():
    costs = EndCosts(out=np.array([[0.0, 3.0], [0.0, 0.0], [1.0, 2.0], [0.1, 0.1]]),
                     inward=np.array([[2.0, 3.0], [0.1, 0.1], [2.0, 2.0], [4.0, 4.0]]),
                     held_share=np.array([[0.2, 0.2], [0.0, 0.0], [0.2, 0.2], [0.9, 0.3]]))
    assert held_from_inside(costs, 0.25, 0.5, 0.5).tolist() == [[True, False], [False, False], [False, False],
                                                                [False, True]]


def forward_views() -> np.ndarray:
    """A camera approaching along +z from 34 to 13 m behind the origin."""
    w2c = []
    for z in (-34.0, -30.0, -26.0, -22.0, -19.0, -16.0, -13.0):
        T = np.eye(4)
        T[2, 3] = -z
        w2c.append(T)
    return np.stack(w2c)


def footprint(box: Box3D, w2c: np.ndarray) -> np.ndarray:
    """The box's car-profile footprint in each view (the projection loss's own projection)."""
    lanes = losses.ProjectionLanes(np.zeros(len(w2c), int), np.zeros(len(w2c)), w2c, np.zeros((len(w2c), 4)),
                                   K, IMAGE_BOUNDS)
    params = {"centre": to_float(box.centre), "size": to_float(box.size), "yaw": to_float(np.array([box.yaw])),
              "velocity": to_float(np.zeros(3)), "dynamic": to_float(np.zeros(1))}
    x1, y1, x2, y2, _ = losses.projected_boxes(InstanceField.decode_parameters(params, 1), lanes, PROFILE)
    return np.stack([np.array(v, dtype=np.float64) for v in (x1, y1, x2, y2)], 1)


@pytest.mark.parametrize("left_open, sweep, length, height, held", [
    (True, True, 4.8, 1.9, [True, False]),    # a neighbour hides the front end: the box ends where most is seen
    (False, True, 4.8, 1.9, [False, False]),  # the masks' front sides are the car's: its length is measured
    (True, False, 4.8, 1.9, [False, False]),  # the front end meets an occluder's edge in every view: a seen end
    (True, True, 5.4, 1.9, [False, False]),   # longer than the visible part: nothing holds the front end
    (True, True, 4.8, 1.2, [True, False]),    # a low car seen to 4.8 m: longer than most (the prior's mean 3.8 m)
    (True, True, 3.6, 1.9, [False, False]),   # a tall one seen to 3.6 m: that says less than the prior
])
def test_a_far_end_hidden_in_every_view_is_held_from_inside(left_open, sweep, length, height, held):
    """A vehicle parked 6 m to the right, seen from behind by an approaching camera. The front end
    (+z) sets each mask box's left side. With ``sweep`` a neighbour hides the front end in every
    view, more of it in some views than in others (0.6 m less to all of the box's ``length``
    seen; for the longer box, of 4.8 m), and the left sides are open (``left_open``): the box
    that ends where the views see most is held from inside at the front only, by one view, and
    is lengthened to the mean length of vehicles at least that long and as tall, its rear face
    kept, unless the bound lies more than ``min_score`` standard deviations below the prior's
    mean. Without ``sweep`` every view sees the same length: an end that meets an occluder's edge
    in the image in every view is the vehicle's own, and is kept."""
    w2c = forward_views()
    rear, seen_most = -1.0, min(length, 4.8)
    seen = np.linspace(seen_most - 0.6, seen_most, len(w2c)) if sweep else np.full(len(w2c), seen_most)
    target = np.stack([footprint(Box3D(centre=np.array([6.0, 0.6, rear + 0.5 * s]), size=np.array([2.1, height, s]),
                                       yaw=0.0), T[None])[0] for s, T in zip(seen, w2c)])
    sides = np.zeros((len(w2c), 4), bool)
    sides[:, 0] = left_open
    lanes = losses.ProjectionLanes(np.zeros(len(w2c), int), np.zeros(len(w2c)), w2c, target, K, IMAGE_BOUNDS, sides)
    loss = projection_box_loss(lanes, 1, LossWeights(), PROFILE, None, np.zeros((1, 3)), np.zeros(1))
    box = Box3D(centre=np.array([6.0, 0.6, rear + 0.5 * length]), size=np.array([2.1, height, length]), yaw=0.0)
    result = estimate_hidden_lengths([box], loss, HELD_ONLY)
    out, ends = result.boxes, result.held
    assert ends.tolist() == [held] and not result.unmeasured.any()
    if any(held):
        want = expected_length(np.array([length]), np.array([height]))[0]
        assert want > length + 0.1
        assert out[0].size[2] == pytest.approx(want)
        assert out[0].centre[2] - 0.5 * out[0].size[2] == pytest.approx(rear)
    else:
        assert out[0] is box


@pytest.mark.parametrize("field, value", [("probe", 0.0), ("min_cost", -1.0), ("free_cost", 0.6),
                                          ("max_held_share", 0.0), ("max_held_share", 1.5), ("min_length", 0.0)])
def test_hidden_length_config_rejects_values_it_cannot_use(field, value):
    with pytest.raises(ValueError, match="hidden_length"):
        HiddenLengthConfig(**{field: value})


def test_boxes_are_told_apart_by_their_own_lanes():
    """Two boxes whose lanes interleave: the first one's front sides closed (its length is
    seen), the second's open with a neighbour sweeping along its front end; only the second is
    lengthened, and the first is returned as it was."""
    w2c = forward_views()
    rear, height = -1.0, 1.9
    seen = np.linspace(4.2, 4.8, len(w2c))
    target = np.stack([footprint(Box3D(centre=np.array([6.0, 0.6, rear + 0.5 * s]), size=np.array([2.1, height, s]),
                                       yaw=0.0), T[None])[0] for s, T in zip(seen, w2c)])
    n = len(w2c)
    box_of_lane = np.tile([0, 1], n)
    sides = np.zeros((2 * n, 4), bool)
    sides[1::2, 0] = True
    lanes = losses.ProjectionLanes(box_of_lane, np.zeros(2 * n), np.repeat(w2c, 2, axis=0),
                                   np.repeat(target, 2, axis=0), K, IMAGE_BOUNDS, sides)
    loss = projection_box_loss(lanes, 2, LossWeights(), PROFILE, None, np.zeros((2, 3)), np.zeros(2))
    boxes = [Box3D(centre=np.array([6.0, 0.6, rear + 2.4]), size=np.array([2.1, height, 4.8]), yaw=0.0,
                   instance_id=k) for k in (7, 8)]
    result = estimate_hidden_lengths(boxes, loss, CFG)
    out, ends = result.boxes, result.held
    assert ends.tolist() == [[False, False], [True, False]] and not result.unmeasured.any()
    assert out[0] is boxes[0]
    assert out[1].instance_id == 8 and out[1].size[2] > 4.9


def hidden_front_loss(seen_most: float, height: float, rear: float = -1.0):
    """The projection loss of one vehicle 6 m to the right of an approaching camera whose front
    end (+z) a neighbour hides in every view, 0.6 m less of it seen in the first view than the
    ``seen_most`` metres the last one sees (the mask boxes' left sides open)."""
    w2c = forward_views()
    seen = np.linspace(seen_most - 0.6, seen_most, len(w2c))
    target = np.stack([footprint(Box3D(centre=np.array([6.0, 0.6, rear + 0.5 * s]), size=np.array([2.1, height, s]),
                                       yaw=0.0), T[None])[0] for s, T in zip(seen, w2c)])
    sides = np.zeros((len(w2c), 4), bool)
    sides[:, 0] = True
    lanes = losses.ProjectionLanes(np.zeros(len(w2c), int), np.zeros(len(w2c)), w2c, target, K, IMAGE_BOUNDS, sides)
    return projection_box_loss(lanes, 1, LossWeights(), PROFILE, None, np.zeros((1, 3)), np.zeros(1))


@pytest.mark.parametrize("length", [5.0, 5.4, 6.6])
def test_a_free_end_moves_in_to_the_visible_part(length):
    """A box reaching past the visible part's 4.8 m: its front end moves in at no cost (beyond
    what the longer box cost) until it reaches where the views see most."""
    loss, rear, height = hidden_front_loss(4.8, 1.9), -1.0, 1.9
    centre, size = np.array([[6.0, 0.6, rear + 0.5 * length]]), np.array([[2.1, height, length]])
    free = np.array([[True, False]])
    travel = free_travel(loss, centre, size, np.zeros(1), free, 0.2, 0.5, 2.7)
    # whole probe steps: the last one that kept the box at least 4.8 m long
    assert travel[0, 1] == 0.0
    assert length - travel[0, 0] == pytest.approx(4.8, abs=0.2 + 1e-9)
    assert length - travel[0, 0] >= 4.8 - 1e-9
    # never past the shortest length allowed
    assert free_travel(loss, centre, size, np.zeros(1), free, 0.2, 0.5, length - 0.2)[0, 0] == pytest.approx(0.2)


@pytest.mark.parametrize("length", [5.0, 5.2])
def test_a_length_no_view_measures_takes_the_mean_above_the_visible_part(length):
    """The same box where its front end is free (moving it out costs < ``free_cost``, in
    nothing; a longer box costs more to lengthen, through the DIoU term): it takes the mean length of vehicles as tall and at
    least as long as the visible part (~4.8 m), shortened or lengthened at its free front end,
    its rear face kept; without the option it keeps its length."""
    loss, rear, height = hidden_front_loss(4.8, 1.9), -1.0, 1.9
    box = Box3D(centre=np.array([6.0, 0.6, rear + 0.5 * length]), size=np.array([2.1, height, length]), yaw=0.0)
    result = estimate_hidden_lengths([box], loss, CFG)
    assert result.unmeasured.tolist() == [True] and not result.held.any()
    got = result.boxes[0]
    low, high = expected_length(np.array([4.6, 4.8]), np.array([height, height]))
    assert low - 1e-9 <= got.size[2] <= high + 1e-9
    assert got.centre[2] - 0.5 * got.size[2] == pytest.approx(rear)
    assert estimate_hidden_lengths([box], loss, HELD_ONLY).boxes[0] is box
    assert not HELD_ONLY.unmeasured


def test_free_ends_cost_nothing_either_way():
    costs = EndCosts(out=np.array([[0.1, 3.0], [0.1, 0.1], [0.1, 0.1]]),
                     inward=np.array([[0.2, 3.0], [2.0, 0.1], [0.6, 0.6]]),
                     held_share=np.zeros((3, 2)))
    assert free_ends(costs, 0.25, 0.5).tolist() == [[True, False], [False, True], [False, False]]


def test_free_travel_stops_at_the_shortest_length():
    """Two free ends of a box no lane sees move in independently down to ``min_length`` each;
    the bound the estimate takes is never below it."""
    loss = LaneLoss(lambda c, s, y: np.zeros(1), np.zeros(1, dtype=np.int64))
    box = Box3D(centre=np.zeros(3), size=np.array([1.8, 1.5, 4.1]), yaw=0.3)
    travel = free_travel(loss, box.centre[None], box.size[None], np.array([0.3]), np.array([[True, True]]), 0.2, 0.5, 2.7)
    assert travel.tolist() == [[pytest.approx(1.4), pytest.approx(1.4)]]
    result = estimate_hidden_lengths([box], loss, CFG)
    assert result.unmeasured.tolist() == [True]
    assert result.boxes[0].size[2] == pytest.approx(expected_length(np.array([2.7]), np.array([1.5]))[0])


def test_move_ends_moves_each_face_on_its_own():
    box = Box3D(centre=np.array([1.0, 0.8, 12.0]), size=np.array([1.8, 1.5, 4.0]), yaw=0.4, instance_id=3)
    axis = np.array([np.sin(0.4), 0.0, np.cos(0.4)])
    out = move_ends([box, box], np.array([[0.5, -0.3], [0.0, 0.0]]))
    assert out[1] is box and out[0].instance_id == 3
    assert out[0].size[2] == pytest.approx(4.2)
    assert out[0].centre + 0.5 * out[0].size[2] * axis == pytest.approx(box.centre + 2.5 * axis)
    assert out[0].centre - 0.5 * out[0].size[2] * axis == pytest.approx(box.centre - 1.7 * axis)


def visible_part_loss(front: float, rear: float, weight: float = 10.0) -> LaneLoss:
    """A lane loss of boxes along z (yaw 0) whose visible part spans ``rear``..``front``: it rises
    as either end moves inside that span, and nothing holds an end outside it (both ends free)."""
    def fn(centre: np.ndarray, size: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        ends_front = centre[:, 2] + 0.5 * size[:, 2]
        ends_rear = centre[:, 2] - 0.5 * size[:, 2]
        return weight * (np.maximum(front - ends_front, 0.0) + np.maximum(ends_rear - rear, 0.0))
    return LaneLoss(fn, np.arange(1))


@pytest.mark.parametrize("centre_z", [0.0, 0.5])
def test_two_free_ends_shorten_without_entering_the_visible_part(centre_z):
    """Both ends of a 6 m box free over a visible part of 4 m: each moves in as far as it may
    (to the visible part, in whole probe steps), the box takes the mean above that bound, and the
    shortening is split by how far each end may move, so neither face enters the visible part."""
    loss = visible_part_loss(2.0, -2.0)
    box = Box3D(centre=np.array([0.0, 0.6, centre_z]), size=np.array([1.8, 1.5, 6.0]), yaw=0.0)
    travel = free_travel(loss, box.centre[None], box.size[None], np.zeros(1), np.array([[True, True]]),
                         0.2, 0.5, 2.7)
    front, rear = 3.0 + centre_z, -3.0 + centre_z
    assert travel[0] == pytest.approx([np.floor((front - 2.0) / 0.2 + 1e-9) * 0.2,
                                       np.floor((-2.0 - rear) / 0.2 + 1e-9) * 0.2])
    result = estimate_hidden_lengths([box], loss, CFG)
    got = result.boxes[0]
    want = expected_length(np.array([6.0 - travel.sum()]), np.array([1.5]))[0]
    assert result.unmeasured.tolist() == [True]
    assert want < 6.0 and got.size[2] == pytest.approx(want)
    assert got.centre[2] + 0.5 * got.size[2] >= 2.0 - 1e-9
    assert got.centre[2] - 0.5 * got.size[2] <= -2.0 + 1e-9
