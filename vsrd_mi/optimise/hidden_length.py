"""Lengths the masks hold from inside only, and the length to label them with.

Where a neighbour (or the image's edge) hides one end of a car in every view, the side of its
mask boxes that the end would set is open, and the projection loss holds the box's end from
inside only: the projection may not fall short of the visible part, but may reach as far as it
likes behind the occluder (:func:`~vsrd_mi.optimise.losses.projection_lane_loss`). Started at
the initialisation's typical length, such a box ends where the visible part of a longer car ends:
the shortest length the masks allow. That is a lower bound, not an estimate, and labelled as one
it makes every long vehicle whose end is hidden short (docs/accuracy.md, "Lengths held from
inside only").

:func:`end_costs` measures, per box and end, what moving the end out and in by a small distance
costs the projection loss, the other end held, summed over the box's views and view by view.
:func:`held_from_inside` reads from them the ends the data holds from inside only: moving the end
out costs nothing measurable, moving it in does, and only in some views (as the camera passes,
an occluder's edge sweeps along the hidden end, and only the views that see most of the car hold
it; a car's own end that merely meets an occluder's edge in the image, its mask's side counted
open all the same, holds in most views). Where moving either end in costs (the box is as short as
the masks allow), :func:`expected_length` gives the box the mean length of vehicles at least as
long as it is, under the catalogue's distribution of lengths given the box's height
(:func:`~vsrd_mi.geometry.vehicle_sizes.length_given_height`): ``E[L | L >= L0]`` of a normal
distribution truncated at ``L0``; :func:`held_steps` moves the held ends out to it. Only bounds no
more than ``min_score`` standard deviations below the prior's mean count: for a bound far below
it the truncated mean is the prior's mean, which would label a short car seen almost whole (a
city car held at 3.1 m) as an average one. A box whose
ends are both measured keeps its length.

An end that moving out costs less than ``free_cost`` and moving in less than ``min_cost`` (the
cost that counts as held; :func:`free_ends`) is measured by no view: the
optimisation leaves it where the initialisation's typical length put it, whatever the vehicle
(development set: such boxes, about one in five, were off by 10 % on average, long vans at 4.5 m,
a few boxes at 6.6 m). With ``HiddenLengthConfig.unmeasured`` (off by default: it made city cars
and moving cars worse on the validation set, docs/accuracy.md) :func:`free_travel` moves each
free end in, step by step, until the masks hold it: the shortest length the masks allow, a lower
bound again. Such a box takes the same :func:`expected_length` of that bound (with no
``min_score`` guard: the length it had carried no measurement either), moving its free ends in
or its unheld ends out (:func:`move_ends`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy.special import erfcx
from vsrd_plugins.sdf import InstanceField

from ..geometry.boxes import Box3D
from ..geometry.vehicle_sizes import length_given_height
from . import losses
from .config import CarProfile, HiddenLengthConfig, LossWeights

#: ``Box3D.size`` index of the length.
_LENGTH = 2
#: ``Box3D.size`` index of the height.
_HEIGHT = 1
#: Rounding (m) allowed where a free end's steps reach the shortest length exactly.
_TOLERANCE = 1e-9

#: Per-lane losses (L,) of boxes given as centres (N, 3), sizes (N, 3) and yaws (N,); each lane
#: is one box in one view (:class:`LaneLoss` says which).
LaneLossFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class LaneLoss:
    """A loss of boxes per lane (``fn``) and the box of each lane (``box``, (L,) ints)."""

    fn: LaneLossFn
    box: np.ndarray

    def per_box(self, values: np.ndarray, count: int) -> np.ndarray:
        """(count,) sums of per-lane ``values`` (L,) over each box's lanes."""
        return np.bincount(self.box, weights=np.asarray(values, dtype=np.float64), minlength=count)


@dataclass(frozen=True)
class EndCosts:
    """Per box and end ((N, 2): the end at ``+axis``, at ``-axis``), what moving the end by the
    probe costs: ``out`` and ``inward`` summed over the box's lanes, and ``held_share``, the share
    of the box's lanes that moving the end in costs at least the ``free_cost`` of
    :func:`end_costs`."""

    out: np.ndarray
    inward: np.ndarray
    held_share: np.ndarray


def axes(yaw: np.ndarray) -> np.ndarray:
    """(N, 3) unit length axes ``(sin yaw, 0, cos yaw)`` (:class:`Box3D`'s convention)."""
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    return np.stack([np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)], axis=1)


def moved_end(centre: np.ndarray, size: np.ndarray, yaw: np.ndarray, end: int, step: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Centres and sizes of the boxes with end ``end`` (0: the one at ``+axis``, 1: at
    ``-axis``) moved out by ``step`` (N,) metres (in where negative), the other end held."""
    sign = 1.0 if end == 0 else -1.0
    step = np.asarray(step, dtype=np.float64).reshape(-1)
    centre = np.asarray(centre, dtype=np.float64) + (sign * 0.5 * step)[:, None] * axes(yaw)
    size = np.array(size, dtype=np.float64)
    size[:, _LENGTH] += step
    return centre, size


def end_costs(loss: LaneLoss, centre: np.ndarray, size: np.ndarray, yaw: np.ndarray, probe: float,
              free_cost: float) -> EndCosts:
    """What moving each box's ends out and in by ``probe`` metres costs (:class:`EndCosts`)."""
    if probe <= 0:
        raise ValueError(f"end_costs: probe must be > 0 m, got {probe}")
    n = len(size)
    lanes = loss.per_box(np.ones(len(loss.box)), n)
    base = np.asarray(loss.fn(centre, size, yaw), dtype=np.float64)
    out, inward, share = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros((n, 2))
    for end in (0, 1):
        for step in (probe, -probe):
            c, s = moved_end(centre, size, yaw, end, np.full(n, step))
            rise = np.asarray(loss.fn(c, s, yaw), dtype=np.float64) - base
            total = loss.per_box(rise, n)
            if step > 0:
                out[:, end] = total
            else:
                inward[:, end] = total
                share[:, end] = loss.per_box(rise >= free_cost, n) / np.maximum(lanes, 1.0)
    return EndCosts(out, inward, share)


def held_from_inside(costs: EndCosts, free_cost: float, min_cost: float, max_held_share: float) -> np.ndarray:
    """(N, 2) bool: ends that moving in costs at least ``min_cost`` (over the box's lanes), in at
    most ``max_held_share`` of its lanes, and moving out less than ``free_cost``. Where the
    length is a bound, an occluder's edge sweeps along the car as the camera passes and only the
    views that see most of it hold the end; a car's own end that merely meets an occluder's
    edge in the image (its mask's side then counts as open too) holds in most views."""
    return (costs.inward >= min_cost) & (costs.out < free_cost) & (costs.held_share <= max_held_share)


def standard_score(lower: np.ndarray, height: np.ndarray,
                   prior: tuple[float, float, float] | None = None) -> np.ndarray:
    """How many of the prior's standard deviations ``lower`` lies above the prior's mean length
    for ``height`` (``prior`` as in :func:`expected_length`)."""
    a, b, sd = length_given_height() if prior is None else prior
    if sd <= 0:
        raise ValueError(f"standard_score: the prior's spread must be > 0 m, got {sd}")
    return (np.asarray(lower, dtype=np.float64) - (a + b * np.asarray(height, dtype=np.float64))) / sd


def expected_length(lower: np.ndarray, height: np.ndarray,
                    prior: tuple[float, float, float] | None = None) -> np.ndarray:
    """``E[L | L >= lower]`` (m) for lengths ``L`` distributed normally about ``a + b * height``
    with standard deviation ``sd`` (``prior = (a, b, sd)``, by default
    :func:`~vsrd_mi.geometry.vehicle_sizes.length_given_height`). Always at least ``lower``."""
    a, b, sd = length_given_height() if prior is None else prior
    alpha = standard_score(lower, height, (a, b, sd))  # refuses a spread <= 0
    lower = np.asarray(lower, dtype=np.float64)
    mu = a + b * np.asarray(height, dtype=np.float64)
    # inverse Mills ratio phi(alpha) / (1 - Phi(alpha)) = sqrt(2 / pi) / erfcx(alpha / sqrt(2)),
    # the scaled complementary error function keeping it finite far in either tail
    mills = np.sqrt(2.0 / np.pi) / erfcx(alpha / np.sqrt(2.0))
    return np.maximum(mu + sd * mills, lower)


def move_ends(boxes: list[Box3D], steps: np.ndarray) -> list[Box3D]:
    """``boxes`` with each end moved out by ``steps`` (N, 2) metres (in where negative; columns
    as in :func:`moved_end`), the box's other faces held; boxes with no step unchanged."""
    steps = np.asarray(steps, dtype=np.float64).reshape(len(boxes), 2)
    out = []
    for box, step in zip(boxes, steps):
        if not step.any():
            out.append(box)
            continue
        centre, size = box.centre[None], np.asarray(box.size, dtype=np.float64)[None]
        for end in np.flatnonzero(step):
            centre, size = moved_end(centre, size, np.array([box.yaw]), int(end), step[end:end + 1])
        out.append(replace(box, centre=centre[0], size=size[0]))
    return out


def held_steps(held: np.ndarray, length: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N, 2) steps for :func:`move_ends` that take boxes of ``length`` (N,) to ``target`` (N,) by
    moving their ``held`` (N, 2) ends out (the growth split between both ends where both are
    held); no step where the target is not longer or no end is held."""
    held = np.asarray(held, dtype=bool).reshape(-1, 2)
    grow = np.maximum(np.asarray(target, dtype=np.float64) - np.asarray(length, dtype=np.float64), 0.0)
    return held * (grow / np.maximum(held.sum(axis=1), 1))[:, None]


def free_ends(costs: EndCosts, free_cost: float, min_cost: float) -> np.ndarray:
    """(N, 2) bool: ends no view measures: moving them out costs less than ``free_cost`` and in
    less than ``min_cost`` (over the box's lanes)."""
    return (costs.out < free_cost) & (costs.inward < min_cost)


def free_travel(loss: LaneLoss, centre: np.ndarray, size: np.ndarray, yaw: np.ndarray, free: np.ndarray,
                probe: float, min_cost: float, min_length: float) -> np.ndarray:
    """(N, 2): how far (m, a multiple of ``probe``) each ``free`` end moves in, the other end
    held, before the box's projection loss (over its lanes) has risen by ``min_cost`` above the
    least it had on the way (a box reaching past its visible part may cost a little, through the
    DIoU term, and shed that as it shortens); never so far that the box is shorter than
    ``min_length``. 0 for the other ends."""
    if probe <= 0 or min_length <= 0:
        raise ValueError(f"free_travel: probe and min_length must be > 0 m, got {probe}, {min_length}")
    n = len(size)
    free = np.asarray(free, dtype=bool).reshape(n, 2)
    travel = np.zeros((n, 2))
    length = np.asarray(size, dtype=np.float64)[:, _LENGTH]
    if not free.any():
        return travel
    base = loss.per_box(loss.fn(centre, size, yaw), n)
    most = int(np.floor(max(0.0, float(length[free.any(axis=1)].max()) - min_length) / probe + _TOLERANCE))
    for end in (0, 1):
        moving, least = free[:, end].copy(), base.copy()
        for k in range(1, most + 1):
            moving &= length - k * probe >= min_length - _TOLERANCE
            if not moving.any():
                break
            c, s = moved_end(centre, size, yaw, end, np.where(moving, -k * probe, 0.0))
            total = loss.per_box(loss.fn(c, s, yaw), n)
            moving &= total - least < min_cost
            least = np.minimum(least, total)
            travel[moving, end] = k * probe
    return travel


def projection_box_loss(lanes: losses.ProjectionLanes, count: int, weights: LossWeights, profile: CarProfile,
                        corner: mi.Float | None, velocity: np.ndarray, dynamic: np.ndarray) -> LaneLoss:
    """The projection loss (:func:`~vsrd_mi.optimise.losses.projection_lane_loss`, with
    ``weights``' settings) of ``count`` boxes on each of ``lanes``, as a function of their
    centres, sizes and yaws; ``velocity`` (count, 3) and ``dynamic`` (count,) stay as given,
    ``corner`` holds the boxes' fitted cuts (None: ``profile.corner``)."""
    lane_box = np.array(lanes.box, dtype=np.int64)
    fixed = {"velocity": mi.Float(np.ravel(velocity)), "dynamic": mi.Float(np.ravel(dynamic))}

    def loss(centre: np.ndarray, size: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        if lanes.count == 0:
            return np.zeros(0)
        params = {"centre": mi.Float(np.ravel(centre)), "size": mi.Float(np.ravel(size)),
                  "yaw": mi.Float(np.ravel(yaw)), **fixed}
        with dr.suspend_grad():
            per_lane = losses.projection_lane_loss(
                InstanceField.decode_parameters(params, count), lanes, weights.huber_beta, weights.projection_huber,
                weights.projection_diou, containment=weights.projection_mode == "containment",
                excess=weights.projection_excess, profile=profile, corner=corner)
        return np.array(per_lane, dtype=np.float64)
    return LaneLoss(loss, lane_box)


@dataclass(frozen=True)
class HiddenLengths:
    """What :func:`estimate_hidden_lengths` did: the boxes, the (N, 2) ends ``held`` from inside
    that it moved out, and the (N,) boxes whose length no view measured (an end free, see
    :func:`free_ends`), set from the prior above the shortest length the masks allow."""

    boxes: list[Box3D]
    held: np.ndarray
    unmeasured: np.ndarray


def estimate_hidden_lengths(boxes: list[Box3D], loss: LaneLoss, cfg: HiddenLengthConfig) -> HiddenLengths:
    """Boxes whose length the masks only bound from below (an end held from inside only, or an
    end no view measures) given :func:`expected_length` of the bound (see the module docstring;
    the thresholds are ``cfg``'s)."""
    n = len(boxes)
    if not boxes:
        return HiddenLengths([], np.zeros((0, 2), dtype=bool), np.zeros(0, dtype=bool))
    centre = np.array([b.centre for b in boxes], dtype=np.float64)
    size = np.array([b.size for b in boxes], dtype=np.float64)
    yaw = np.array([b.yaw for b in boxes], dtype=np.float64)
    length, height = size[:, _LENGTH], size[:, _HEIGHT]
    costs = end_costs(loss, centre, size, yaw, cfg.probe, cfg.free_cost)
    # the length is a bound only where moving either end in costs (the box is as short as the
    # masks allow); an end held from inside beside one that could move in freely bounds nothing
    pinned = np.all(costs.inward >= cfg.min_cost, axis=1)
    # a bound far below the prior's mean says nothing the prior does not, and the mean would
    # label a short car seen almost whole as an average one
    informative = standard_score(length, height) >= cfg.min_score
    target = expected_length(length, height)
    held = (held_from_inside(costs, cfg.free_cost, cfg.min_cost, cfg.max_held_share)
            & (pinned & informative & (target > length))[:, None])
    steps = held_steps(held, length, target)
    unmeasured = np.zeros(n, dtype=bool)
    if cfg.unmeasured:
        free = free_ends(costs, cfg.free_cost, cfg.min_cost)
        travel = free_travel(loss, centre, size, yaw, free, cfg.probe, cfg.min_cost, cfg.min_length)
        bound = np.maximum(length - travel.sum(axis=1), np.minimum(cfg.min_length, length))
        change = np.where(free.any(axis=1), expected_length(bound, height) - length, 0.0)
        change = np.where(np.abs(change) > _TOLERANCE, change, 0.0)
        # growth goes to the ends nothing holds from outside, shortening to the free ends in
        # proportion to how far each may move in (together at most the box's length less the bound)
        movable_out = costs.out < cfg.free_cost   # free ends among them
        share_out = movable_out / np.maximum(movable_out.sum(axis=1), 1)[:, None]
        share_in = travel / np.maximum(travel.sum(axis=1), 1e-12)[:, None]
        steps = steps + np.where((change > 0)[:, None], share_out, share_in) * change[:, None]
        unmeasured = change != 0.0
    return HiddenLengths(move_ends(boxes, steps), held, unmeasured)


__all__ = ["EndCosts", "HiddenLengths", "LaneLoss", "LaneLossFn", "axes", "end_costs", "estimate_hidden_lengths",
           "expected_length", "free_ends", "free_travel", "held_from_inside", "held_steps", "move_ends", "moved_end",
           "projection_box_loss", "standard_score"]
