"""The adaptive sampler: band samples of the rays that meet an enlarged box, each evaluated only for
the instances that ray meets, then the NeuS integral (:mod:`.integral`).

With the residual field, samples whose derivative vanishes (strictly inside a monotone run of the
scene SDF, one instance near) keep their values but leave the AD graph (:func:`frozen_lanes`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..common import block_successor, concat_groups
from ..sdf import RIDGE_TOLERANCE
from .bands import adaptive_bands
from .integral import integrate, log_transmittance, sample_points
from .layout import adaptive_groups
from .residual_search import ChordGrid
from .settings import SamplingContext
from .slots import SampleGroup

#: Stand-in SDF value of an isolated ray's other bands' instances at a band's samples (beyond
#: any culling margin: out of the scene SDF's minimum and the softmin).
ISOLATED_ELSEWHERE = 1e6
#: Sparse gradients: a sample is frozen only where its scene SDF differs from both neighbours'
#: by more than this (m). The detached values (fused MLP) and the graph's (tensor-mode MLP)
#: differ in rounding, and samples moved to an extremum often sit within 1e-7 of a neighbour:
#: without the margin such a pair could be ordered one way in the detached values and the other
#: in the graph, freezing a sample the graph sees as the minimum.
MONOTONE_TOLERANCE = 1e-5
#: Monotone margin (m) with which interpolated values sort samples into frozen or not
#: (:func:`grid_values`): above the chord grid's interpolation error (p9999 9e-4 m).
GRID_TOLERANCE = 1e-3
#: Above the float32 difference (m) between a lane's box SDF from its box-local ray
#: (:class:`~.residual_search.ChordGrid`) and from its world-frame point
#: (:meth:`~vsrd_plugins.sdf.InstanceField.lane_sdfs`).
REACH_ROUNDING = 1e-4


def render_adaptive(ctx: SamplingContext, dec, o, d, time) -> list[mi.Float] | None:
    """Band samples of the rays that meet an enlarged box; at each sample only the instances
    whose enlarged box the ray meets (one SDF evaluation per lane and met instance)."""
    n_rays, n_inst = dr.width(o.x), ctx.field.n
    bands = adaptive_bands(ctx, dec, o, d, time)
    grid = bands.grid
    groups = list(adaptive_groups(ctx, bands))
    if not groups:
        return None
    # one flat list of (point, time, instance) lanes for every group and band slot, so the
    # SDF (and the residual MLP) is evaluated in one batch
    with dr.suspend_grad():
        # per group the pieces (one per band slot, one for an isolated group)
        ray_lanes, ts, insts, deep, pairs = [], [], [], [], []
        kink_lams = []  # per lane, as deep: a kink's own weight (-1: none)
        for grp in groups:
            t, m, own, slot_inst = grp.t, grp.m, grp.own, grp.inst
            r = dr.arange(mi.UInt32, dr.width(t)) // m
            ray_of = dr.gather(mi.UInt32, grp.rays, r)
            # an isolated group's samples evaluate their own band's instance only
            bands_of = [own] if own is not None else [mi.UInt32(b) for b in range(len(slot_inst))]
            if grid is not None:  # each lane's (slot, ray) pair of the chord grid
                row_of = dr.gather(mi.UInt32, grp.rows, r)
                pairs.append([row_of + b * dr.opaque(mi.UInt32, grid.rays) for b in bands_of])
            if own is not None:
                inst_own = mi.UInt32(0)
                for b, ib in enumerate(slot_inst):
                    inst_own = dr.select(own == b, dr.gather(mi.UInt32, ib, r), inst_own)
                insts.append([inst_own])
            else:
                insts.append([dr.gather(mi.UInt32, ib, r) for ib in slot_inst])
            ray_lanes.append([ray_of] * len(bands_of))
            ts.append([t] * len(bands_of))
            deep.append([dr.select(grp.deepest == b, 1, 0) for b in bands_of])
            kink_lams.append([dr.select(grp.deepest == b, grp.kink_lam, -1.0) for b in bands_of])
        ray_all = concat_groups(ray_lanes)
        s_all = concat_groups(ts)
        p_all, t_all, d_all = sample_points(ray_all, o, d, time, s_all, 1)
        i_all = concat_groups(insts)
        # lanes at the deepest point of their ray in their instance's box, or at a kink of
        # it where B + R has a minimum (ridge gradients; a kink with its own weight)
        deep = dr.compress(concat_groups(deep) > 0)
        ridge = None
        if ctx.settings.ridge_gradients and dr.width(deep):
            ridge = (deep, dr.gather(mi.Vector3f, d_all, deep), RIDGE_TOLERANCE,
                     dr.gather(mi.Float, concat_groups(kink_lams), deep))
    # beyond the culling margin of its box a lane's SDF cannot move the integral by more
    # than exp(-reach) (see SamplingContext.cull_margin): its value is kept, its gradient dropped
    weights = ctx.field.residual_weights()
    kw = dict(reach=ctx.residual_reach(), grad_reach=dr.detach(ctx.cull_margin()))
    values = frozen = None
    if weights is not None and ctx.settings.residual_sparse_gradients:
        with dr.suspend_grad():
            if grid is not None:
                values = grid_values(ctx, dec, grid, concat_groups(pairs), s_all, p_all, t_all, i_all,
                                     groups, deep, weights, kw)
            else:
                values = ctx.field.lane_sdfs(dec, p_all, t_all, i_all, weights, **kw)
            frozen = frozen_lanes(ctx, values, groups, deep)
    f_all = ctx.field.lane_sdfs(dec, p_all, t_all, i_all, weights, ridge=ridge, values=values,
                                frozen=frozen, **kw)
    flat = dr.zeros(mi.Float, n_rays * n_inst)
    start = 0
    for grp in groups:
        t, m, own, slot_inst = grp.t, grp.m, grp.own, grp.inst
        w = dr.width(t)
        with dr.suspend_grad():
            lane = dr.arange(mi.UInt32, w)
        # each slot's SDFs are a slice of f_all: no two lanes of any of these gathers read
        # the same entry, so their reverse (a scatter-add) needs no atomics
        slices = [dr.gather(mi.Float, f_all, lane + dr.opaque(mi.UInt32, start + b * w),
                            mode=dr.ReduceMode.NoConflicts)
                  for b in range(1 if own is not None else len(slot_inst))]
        start += w * len(slices)
        # on an isolated ray every other band's box is beyond its culling margin at a
        # sample (see bands.isolated_rays): it is left out of the minimum and the softmin there
        sdfs = slices if own is None else [dr.select(own == b, slices[0], ISOLATED_ELSEWHERE)
                                           for b in range(len(slot_inst))]
        peak = grp.peak if ctx.settings.ridge_gradients else None
        for lab, ib in zip(integrate(sdfs, m, ctx.sharpness, ctx.temperature, peak), slot_inst):
            dr.scatter_add(flat, lab, grp.rays * n_inst + ib, grp.active)
        ctx.count(grp.real, m, len(slices))
    idx = dr.arange(mi.UInt32, n_rays) * n_inst
    return [dr.gather(mi.Float, flat, idx + k) for k in range(n_inst)]


def grid_values(ctx: SamplingContext, dec, grid: ChordGrid, pairs: mi.UInt32, s: mi.Float, p: mi.Point3f,
                time: mi.Float, inst: mi.UInt32, groups: list[SampleGroup], deep: mi.UInt32, weights, kw: dict) -> mi.Float:
    """Detached SDF values of :func:`render_adaptive`'s lanes (``pairs``: each lane's (slot,
    ray) pair of ``grid``; ``s``: its ray parameter; ``p``, ``time``, ``inst``: its point,
    ray time and instance) for :func:`frozen_lanes`: ``B`` exact and ``R`` interpolated from
    the chord grid, exact where it can matter.

    A frozen lane's value drops out of the integral (it lies strictly inside a monotone run
    of ``f``, whose opacity telescopes to the run's ends), as long as it keeps the run
    monotone; the lanes that keep their gradient are the run's ends and get exact values in
    the AD graph. So the interpolated values sort the lanes with a margin of
    :data:`GRID_TOLERANCE` (above the interpolation error: p99 5e-5 m, p9999 9e-4 m at the
    samples), the lanes that stay in the graph under it and their neighbours (whose order
    against them decides where a run ends) get exact values, and :func:`render_adaptive`
    sorts the lanes again with them. With the plain margin a shallow extremum of the
    exact ``B + R`` that the interpolation smooths out stayed frozen: sparse vs full-graph
    box gradient 4.2e-2 relative on the benchmark's 3-box scene, now 3.4e-4 (exact values
    everywhere: 6.8e-4; ``test_residual_grid_keeps_the_sparse_gradient``). 6 boxes / 16k
    rays: 0.26M exact residuals instead of 1.06M.
    """
    values, box = grid.sdf_within(pairs, s, kw["reach"])
    dr.eval(values, box)  # one kernel for both
    frozen = frozen_lanes(ctx, values, groups, deep, GRID_TOLERANCE)
    # beyond the reach a value is the exact B already (a margin keeps the lanes whose B the
    # world-frame evaluation of lane_sdfs could put on the other side of the reach)
    border = run_ends(frozen, groups) & (box <= kw["reach"] + REACH_ROUNDING)
    idx = dr.compress(border)
    if dr.width(idx):
        exact = ctx.field.lane_sdfs(dec, dr.gather(type(p), p, idx), dr.gather(mi.Float, time, idx),
                                    dr.gather(mi.UInt32, inst, idx), weights, **kw)
        dr.scatter(values, exact, idx)
    dr.eval(values)
    return values


def run_ends(frozen: mi.Bool, groups: list[SampleGroup]) -> mi.Bool:
    """Lanes of :func:`render_adaptive`'s flat layout that are not ``frozen``
    (:func:`frozen_lanes`) or neighbour such a lane along their ray."""
    border = dr.zeros(mi.Bool, dr.width(frozen))
    start = 0
    for grp in groups:
        w, m = dr.width(grp.t), grp.m
        lane = dr.arange(mi.UInt32, w)
        j = lane % m
        for _ in range(1 if grp.own is not None else len(grp.inst)):
            at = lane + dr.opaque(mi.UInt32, start)
            live = ~dr.gather(mi.Bool, frozen, at)
            live |= (j > 0) & ~dr.gather(mi.Bool, frozen, dr.select(j > 0, at - 1, at))
            live |= (j < m - 1) & ~dr.gather(mi.Bool, frozen, dr.select(j < m - 1, at + 1, at))
            dr.scatter(border, live, at)
            start += w
    return border


def frozen_lanes(ctx: SamplingContext, values: mi.Float, groups: list[SampleGroup], deep: mi.UInt32,
                 tolerance: float = MONOTONE_TOLERANCE) -> mi.Bool:
    """Lanes of :func:`render_adaptive`'s flat layout whose SDF value cannot carry a
    gradient of the integral (detached ``values`` of every lane in).

    The opacity telescopes over each monotone run of the scene SDF ``f`` along a ray:
    ``sum_i log(1 - alpha_i) = log Phi_s(f_end) - log Phi_s(f_start)`` over a descent, and 0
    over an ascent, so a sample strictly inside a run (``f`` strictly monotone through it)
    has zero derivative there. Its labels are the opacity times the softmin shares; where
    only one instance is within the culling margin at a sample and at both neighbours, the
    shares are 1 and 0 up to ``exp(-reach)`` (the culling bound), and the labels' derivative
    vanishes with the opacity's. Those samples keep their values but leave the AD graph
    (and the residual MLP's backward pass). Ends of rays, extrema, ties, the deepest points
    (ridge gradients) and every sample next to a mixed one stay. Samples behind a surface
    that has taken the transmittance below ``exp(-reach)`` (the culling bound) before the
    interval that ends at them leave the graph too: every term their value enters carries
    that weight (6 boxes / 16k rays: 94k -> 86k samples in the graph; sparse vs full-graph
    gradients unchanged at 3, 6 and 12 boxes). ``tolerance``: the margin by which a run must
    be monotone.
    """
    frozen = dr.zeros(mi.Bool, dr.width(values))
    margin = dr.detach(ctx.cull_margin())
    s = dr.detach(ctx.sharpness)
    start = 0
    for grp in groups:
        t, m = grp.t, grp.m
        w = dr.width(t)
        n_slots = 1 if grp.own is not None else len(grp.inst)
        lane = dr.arange(mi.UInt32, w)
        j = lane % m
        slots = [dr.gather(mi.Float, values, lane + dr.opaque(mi.UInt32, start + b * w)) for b in range(n_slots)]
        f = slots[0]
        near = dr.select(slots[0] <= margin, 1, 0)
        for fb in slots[1:]:
            f = dr.minimum(f, fb)
            near += dr.select(fb <= margin, 1, 0)
        mixed = near >= 2
        inner = (j > 0) & (j < m - 1)
        prev, nxt = dr.select(inner, lane - 1, lane), dr.select(inner, lane + 1, lane)
        f_prev, f_next = dr.gather(mi.Float, f, prev), dr.gather(mi.Float, f, nxt)
        eps = tolerance
        monotone = (((f_prev > f + eps) & (f > f_next + eps))
                    | ((f_prev + eps < f) & (f + eps < f_next)))
        free = (inner & monotone & ~mixed & ~dr.gather(mi.Bool, mixed, prev)
                & ~dr.gather(mi.Bool, mixed, nxt))
        # behind a surface that took the transmittance below exp(-reach): every term a
        # sample's value enters is weighted by the transmittance before the interval that
        # ends at it (the culling bound)
        f_after = dr.gather(mi.Float, f, block_successor(w, m))
        log_t, _ = log_transmittance(s, f, f_after, j == m - 1, m)
        shadowed = (j > 0) & (dr.gather(mi.Float, log_t, dr.select(j > 0, lane - 1, lane)) < -ctx.settings.reach)
        free |= shadowed
        for b in range(n_slots):
            dr.scatter(frozen, free, lane + dr.opaque(mi.UInt32, start + b * w))
        start += w * n_slots
    if dr.width(deep):
        dr.scatter(frozen, False, deep)
    return frozen
