"""Occlusion-aware projection loss: the open sides of a mask box (vsrd_mi.data.masks.open_sides)
and the one-sided residual they get (vsrd_mi.optimise.losses.projection_loss)."""

from __future__ import annotations

import numpy as np
import pytest

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins import box_properties
from vsrd_plugins.sdf import InstanceField
from vsrd_mi.data.masks import BEHIND_MARGIN_PX, lowest_rows, occluder_map, open_sides
from vsrd_mi.optimise import losses

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
BOUNDS = np.array([-0.5, -0.5, 639.5, 479.5])
CAR, OTHER_CAR, ROAD, POLE, BUILDING, VEGETATION, PERSON, SIGN = 26001, 26002, 7, 17, 11, 21, 24001, 20001


def instance_map() -> np.ndarray:
    m = np.full((60, 100), ROAD, dtype=np.uint16)
    m[:20] = BUILDING
    m[20:40, 30:70] = CAR
    return m


def test_a_lone_car_has_no_open_side():
    m = instance_map()
    assert not open_sides(m == CAR, occluder_map(m)).any()


def test_a_car_in_front_opens_the_side_it_covers():
    m = instance_map()
    m[15:45, 60:80] = OTHER_CAR             # in front, over the right end
    assert open_sides(m == CAR, occluder_map(m)).tolist() == [False, False, True, False]


def test_poles_open_a_side_but_buildings_do_not():
    m = instance_map()
    m[:, 28:30] = POLE                      # a pole right beside the left end
    assert open_sides(m == CAR, occluder_map(m)).tolist() == [True, False, False, False]
    m = instance_map()
    m[20:40, 70:75] = BUILDING              # behind the car: no occluder
    assert not open_sides(m == CAR, occluder_map(m)).any()


def test_things_standing_behind_a_car_leave_its_sides_closed():
    """A car further down the street borders a nearer car's roof in the image: its lowest visible
    row lies above the nearer car's, so it stands behind it and the roof stays a constraint."""
    m = instance_map()                      # CAR: rows 20-39
    m[14:20, 20:80] = OTHER_CAR             # further away: lowest row 19, 20 rows above the car's
    lowest = lowest_rows(m)
    assert lowest[:, 15, 25].tolist() == [19, 19] and lowest[:, 30, 40].tolist() == [39, 39]
    assert lowest[:, 0, 0].tolist() == [m.shape[0]] * 2
    assert open_sides(m == CAR, occluder_map(m)).tolist() == [False, True, False, False]  # unordered
    assert not open_sides(m == CAR, occluder_map(m), lowest).any()
    # the other car reaching down to the car's bottom row (within the margin) beside its right
    # end may stand in front of it: the right side opens, and the roof it borders too
    m[20:40 - BEHIND_MARGIN_PX, 70:80] = OTHER_CAR
    assert open_sides(m == CAR, occluder_map(m), lowest_rows(m)).tolist() == [False, True, True, False]
    # a sign in front: its pole reaches below the car's bottom, its board hangs over the roof
    m = instance_map()
    m[12:20, 40:60] = SIGN                  # the board, over the roof (its columns end at row 19)
    m[20:50, 49:51] = SIGN                  # the pole, in front of the car down to the ground
    assert open_sides(m == CAR, occluder_map(m), lowest_rows(m))[1]
    # a person in front (feet below the car's bottom) opens the side it covers; one behind does not
    m = instance_map()
    m[10:45, 25:30] = PERSON
    assert open_sides(m == CAR, occluder_map(m), lowest_rows(m)).tolist() == [True, False, False, False]
    m = instance_map()
    m[5:20, 25:32] = PERSON                 # above the roof line: its legs hidden by the car
    m[20:30, 25:30] = PERSON
    assert not open_sides(m == CAR, occluder_map(m), lowest_rows(m)).any()
    # stuff is not ordered: a tree crown above the roof still opens it
    m = instance_map()
    m[10:20, 20:80] = VEGETATION
    assert open_sides(m == CAR, occluder_map(m), lowest_rows(m)).tolist() == [False, True, False, False]


def test_an_occluder_meeting_the_end_at_a_slant_opens_it():
    """A car in front whose top edge meets the car's end below its outermost pixels (a rear
    window sloping down behind a nearer car's roof) hides the rest of the end: looking only
    straight outwards from the outermost pixels finds the sky there, looking within 45 degrees
    of outwards finds the car in front."""
    m = instance_map()                      # CAR: rows 20-39, columns 30-69
    m[20:40, 66:70] = ROAD
    m[20:23, 66:70] = CAR                   # the end's outermost pixels: a tip, rows 20-22
    m[23:45, 66:90] = OTHER_CAR             # in front (lower bottom), its top edge just below the tip
    assert open_sides(m == CAR, occluder_map(m), lowest_rows(m)).tolist() == [False, False, True, False]
    m[23:45, 66:90] = ROAD                  # nothing beside the tip: the end stays a constraint
    assert not open_sides(m == CAR, occluder_map(m), lowest_rows(m)).any()


def test_the_image_edge_opens_a_truncated_side_and_its_top_and_bottom():
    """Beyond the image's edge the car may reach higher (its roof) and lower (its nearest wheel)."""
    m = instance_map()
    m[20:40, 0:30] = CAR                    # the car reaches the left image edge
    assert open_sides(m == CAR, occluder_map(m)).tolist() == [True, True, False, True]
    m = instance_map()
    m[20:40, 70:100] = CAR                  # and the right one
    assert open_sides(m == CAR, occluder_map(m)).tolist() == [False, True, True, True]
    m = instance_map()
    m[15:45, 60:80] = OTHER_CAR             # cut by a car in front instead: top and bottom stay
    assert open_sides(m == CAR, occluder_map(m), lowest_rows(m)).tolist() == [False, False, True, False]


def test_a_few_occluded_edge_pixels_do_not_open_a_side():
    m = instance_map()
    m[38:40, 70:72] = POLE                  # 2 of the right side's 40 outermost pixels
    assert not open_sides(m == CAR, occluder_map(m)).any()
    assert not open_sides(np.zeros((5, 5), bool), np.zeros((5, 5), bool)).any()


def huber(x: float, beta: float) -> float:
    return 0.5 * x * x / beta if abs(x) < beta else abs(x) - 0.5 * beta


def test_open_sides_only_bound_the_projection_from_inside():
    """A box straight ahead projects to (288.75, 202.5, 413.75, 302.5) (see test_losses); against a
    mask box that it overshoots on the left and falls short of on the right, an open left side costs
    nothing and an open right side costs what a closed one does; the DIoU term leaves open lanes."""
    p = mi.Properties()
    for k, v in box_properties(np.array([[0.5, 0.2, 10.0]]), np.array([[2.0, 1.6, 4.0]]), np.array([0.0])).items():
        p[k] = v
    dec = InstanceField(p, "test").decode()
    pred = np.array([288.75, 202.5, 413.75, 302.5])
    mask = np.array([295.0, 202.5, 420.0, 302.5])  # left: pred 6.25 px outside; right: 6.25 px short
    beta, w_huber, w_diou = 1.0, 1.0, 0.1

    def loss(sides) -> float:
        lanes = losses.ProjectionLanes(np.array([0]), np.zeros(1), np.eye(4)[None], mask[None], K, BOUNDS,
                                       np.array([sides], bool))
        return float(np.array(dr.detach(losses.projection_loss(dec, lanes, beta, w_huber, w_diou)))[0])

    closed = loss([False] * 4)
    left_open = loss([True, False, False, False])
    right_open = loss([False, False, True, False])
    e = pred - mask
    assert left_open == pytest.approx(w_huber * huber(e[2], beta), rel=1e-4)      # DIoU and left gone
    assert right_open == pytest.approx(w_huber * (huber(e[0], beta) + huber(e[2], beta)), rel=1e-4)
    assert closed > right_open                     # the closed lane also pays the DIoU term
