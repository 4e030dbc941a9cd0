"""The adaptive sampler: band samples of the rays that meet an enlarged box, each evaluated only for
the instances that ray meets, then the NeuS integral (:mod:`.integral`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..common import concat_groups
from ..sdf import RIDGE_TOLERANCE
from .bands import adaptive_bands
from .integral import integrate, sample_points
from .layout import adaptive_groups
from .settings import SamplingContext

#: Stand-in SDF value of an isolated ray's other bands' instances at a band's samples (beyond
#: any culling margin: out of the scene SDF's minimum and the softmin).
ISOLATED_ELSEWHERE = 1e6


def render_adaptive(ctx: SamplingContext, dec, o, d, time) -> list[mi.Float] | None:
    """Band samples of the rays that meet an enlarged box; at each sample only the instances
    whose enlarged box the ray meets (one SDF evaluation per lane and met instance)."""
    n_rays, n_inst = dr.width(o.x), ctx.field.n
    groups = list(adaptive_groups(ctx, adaptive_bands(ctx, dec, o, d, time)))
    if not groups:
        return None
    # one flat list of (point, time, instance) lanes for every group and band slot, so the
    # SDF (and the residual MLP) is evaluated in one batch
    with dr.suspend_grad():
        # per group the pieces (one per band slot, one for an isolated group)
        ray_lanes, ts, insts, deep = [], [], [], []
        kink_lams = []  # per lane, as deep: a kink's own weight (-1: none)
        for grp in groups:
            t, m, own, slot_inst = grp.t, grp.m, grp.own, grp.inst
            r = dr.arange(mi.UInt32, dr.width(t)) // m
            ray_of = dr.gather(mi.UInt32, grp.rays, r)
            # an isolated group's samples evaluate their own band's instance only
            bands_of = [own] if own is not None else [mi.UInt32(b) for b in range(len(slot_inst))]
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
    f_all = ctx.field.lane_sdfs(dec, p_all, t_all, i_all, ctx.field.residual_weights(), reach=ctx.residual_reach(),
                                ridge=ridge, grad_reach=dr.detach(ctx.cull_margin()))
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

