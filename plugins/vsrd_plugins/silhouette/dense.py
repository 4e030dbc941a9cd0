"""The dense sampler (the paper's reference) and the integral at given samples.

``coarse_samples`` stratified samples over ``[near, far]`` (no gradients), then ``fine_samples``
importance samples from the coarse weights (guarded against rays whose coarse weights vanish),
merged in order; every instance is evaluated at every sample. :func:`integrate_at` runs the
same integral at any given sorted samples (the converged references of the tests and benchmarks).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..common import block_predecessor, block_successor
from ..sdf import RIDGE_TOLERANCE, scene_sdf
from .integral import integrate, interval_weights, sample_points
from .settings import SamplingContext

#: Importance sampling: a uniform floor of this fraction of a ray's coarse weight per interval
#: keeps rays whose weights vanish from dividing by ~0.
PDF_FLOOR = 1e-3


def render_dense(ctx: SamplingContext, dec, o, d, time) -> list[mi.Float]:
    """Every instance at every one of the ``coarse + fine`` samples of every ray."""
    n_rays = dr.width(o.x)
    t, m = dense_positions(ctx, dec, o, d, time)
    labels = integrate_at(ctx, dec, dr.arange(mi.UInt32, n_rays), o, d, time, t, m)
    ctx.count(n_rays, m, ctx.field.n)
    return labels


def integrate_at(ctx: SamplingContext, dec, ray_idx: mi.UInt32, o, d, time, t: mi.Float, m: int) -> list[mi.Float]:
    """Labels of rays ``ray_idx`` from the NeuS integral at given sorted samples ``t``
    (``m`` per ray): the integral both strategies use, for references and tests."""
    p, tg, dirs = sample_points(ray_idx, o, d, time, t, m)
    sdfs = ctx.field.instance_sdfs(dec, p, tg, ctx.field.residual_weights(), reach=ctx.residual_reach())
    return integrate(deepest_sample_ridges(ctx, dec, sdfs, p, tg, dirs, t, m), m, ctx.sharpness, ctx.temperature)


def deepest_sample_ridges(ctx: SamplingContext, dec, sdfs: list[mi.Float], p, time, dirs, t: mi.Float, m: int) -> list[mi.Float]:
    """Give each ray's deepest sample inside each box the envelope gradient of the box's
    minimum along the ray (:func:`~vsrd_plugins.sdf.box_sdf_ray_local`), as the adaptive
    sampler does at its exact deepest point: the sampled minimum stands in for the true one,
    within a face tolerance of twice the local sample spacing (slopes are at most 1)."""
    if not ctx.settings.ridge_gradients:
        return sdfs
    with dr.suspend_grad():
        lane = dr.arange(mi.UInt32, dr.width(t))
        t_next = dr.gather(mi.Float, t, block_successor(dr.width(t), m))
        t_prev = dr.gather(mi.Float, t, block_predecessor(dr.width(t), m))
        tol = dr.maximum(2.0 * dr.maximum(t_next - t, t - t_prev), RIDGE_TOLERANCE)
        ray = lane // m
    out = []
    for k, f in enumerate(sdfs):
        with dr.suspend_grad():
            fmin = dr.block_reduce(dr.ReduceOp.Min, dr.detach(f), m)
            lanes = dr.compress((dr.detach(f) <= dr.gather(mi.Float, fmin, ray)) & (dr.detach(f) < 0.0))
        if dr.width(lanes) == 0:
            out.append(f)
            continue
        ridge = (lanes, dr.gather(mi.Vector3f, dirs, lanes), dr.gather(mi.Float, tol, lanes))
        out.append(f + ctx.field.ridge_correction(dec, p, time, mi.UInt32(k), ridge))
    return out


def dense_positions(ctx: SamplingContext, dec, o, d, time) -> tuple[mi.Float, int]:
    """Coarse stratified + importance samples, merged in order (detached)."""
    cfg = ctx.settings
    nc, nf = cfg.coarse_samples, cfg.fine_samples
    n = dr.width(o.x)
    with dr.suspend_grad():
        lane = dr.arange(mi.UInt32, n * nc)
        r, i = lane // nc, lane % nc
        step = (cfg.far - cfg.near) / (nc - 1)
        tc = cfg.near + mi.Float(i) * step
        p = dr.gather(mi.Point3f, o, r) + tc * dr.gather(mi.Vector3f, d, r)
        tg = dr.gather(mi.Float, time, r)
        f = scene_sdf(ctx.field.instance_sdfs(dec, p, tg, ctx.field.residual_weights(),
                                               reach=ctx.residual_reach()))
        last = i == (nc - 1)
        f_next = dr.gather(mi.Float, f, block_successor(n * nc, nc))
        w, _ = interval_weights(ctx.sharpness, f, f_next, last, nc)
        # pdf over the nc - 1 intervals; a uniform floor guards rays whose weights vanish
        # (a division by ~1e-6 would send their samples to 1e6 m)
        total = dr.block_sum(w, nc)
        floor = PDF_FLOOR * dr.maximum(dr.gather(mi.Float, total, r), 1e-8) / (nc - 1)
        pdf = dr.select(last, 0.0, w + floor)
        cdf = dr.block_prefix_sum(pdf, nc, exclusive=False)
        norm = dr.gather(mi.Float, cdf, r * nc + (nc - 1))
        cdf = cdf / norm  # cdf[i] = P(interval <= i)
        # fine samples: u_j = (j + 0.5) / nf, bin = first interval with cdf >= u
        flane = dr.arange(mi.UInt32, n * nf)
        fr, fj = flane // nf, flane % nf
        u = (mi.Float(fj) + 0.5) / nf
        base = fr * nc
        b = dr.binary_search(0, nc - 2, lambda idx: dr.gather(mi.Float, cdf, base + idx) < u)
        c_hi = dr.gather(mi.Float, cdf, base + b)
        c_lo = dr.select(b > 0, dr.gather(mi.Float, cdf, base + b - 1), 0.0)
        frac = dr.clip((u - c_lo) / dr.maximum(c_hi - c_lo, 1e-12), 0.0, 1.0)
        tf = cfg.near + (mi.Float(b) + frac) * step
        # merge: fine j sits after coarse samples 0..b, coarse i after the fine samples in bins < i
        m = nc + nf
        fine_pos = fr * m + fj + b + 1
        hist = dr.zeros(mi.UInt32, n * nc)
        dr.scatter_add(hist, mi.UInt32(1), base + b)
        before = dr.block_prefix_sum(hist, nc, exclusive=True)
        coarse_pos = r * m + i + before
        t = dr.zeros(mi.Float, n * m)
        dr.scatter(t, tc, coarse_pos)
        dr.scatter(t, tf, fine_pos)
    return t, m
