"""The residual search: where the instance SDF ``F = B + R`` has its minima, extrema and crossings.

With the residual field ``F = B + R`` along a ray is no longer convex: its minimum moves off the
box's, it can dip more than once, and ``R`` turns kinks of ``B`` into minima. The detached
searches here run over the (slot, ray) pairs that hold a box (:class:`PairScan`) and read ``F``
with ``B`` exact and ``R`` interpolated from exact values on a grid along each pair's chord
(:class:`ChordGrid`): ``R`` is smooth at the scale of its encoding's highest frequency, while
``B`` carries every kink of ``F``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..common import block_of, compress_wide, concat, golden_minimum, illinois_root, pick
from ..sdf import LATTICE_LOOKUP_COST, ResidualLattice, box_sdf_local, envelope_weight
from .settings import SamplingContext
from .slots import KINK_MINIMA, GapPeak, Picked

#: Fewest grid points per chord of :func:`chord_grid`.
GRID_MIN_POINTS = 4
#: Probe distance (m) on either side of a kink of ``B`` (:func:`kink_minima`).
KINK_PROBE = 1e-3
#: Golden-section steps that find the minimum of ``B + R`` beside a bend of ``B`` (or beside a
#: kink, off it) between two of its probes (:func:`kink_minima`), and an extremum of a chord
#: between its scan points: the bracket shrinks 320x, to well under a millimetre for the widest
#: bends.
KINK_GOLDEN = 12
#: Regula falsi steps (Illinois) that move a gap peak to the crossing of two instance SDFs
#: ``B + R`` (:func:`residual_peaks`); they converge superlinearly where ``F_a - F_a'`` is smooth
#: (bisection from 10 m to 10 um takes 20).
PEAK_STEPS = 8


@dataclass(frozen=True)
class ChordGrid:
    """Exact residuals ``R`` on a grid over each (slot, ray) pair's enlarged-box chord, and
    ``F = B + R`` from them with ``B`` exact and ``R`` interpolated (Catmull-Rom: C1, exact for
    quadratics), built by :func:`chord_grid` (detached arrays; pairs
    slot-major, ``rays`` per slot)."""

    views: tuple  #: per pair the box-local ray origin, direction and half size
    start: mi.Float  #: per pair the chord's start (the enlarged box's entry)
    inv_step: mi.Float  #: per pair 1 / grid spacing (0 for an empty chord)
    points: mi.UInt32  #: per pair its grid points (0: an invalid slot)
    first: mi.UInt32  #: per pair the index of its first grid point in ``r``
    r: mi.Float  #: the residual at every grid point
    rays: int  #: rays per slot
    pairs: mi.UInt32  #: the pairs that hold a box (grid points > 0), for :class:`PairScan`
    rank: mi.UInt32  #: per pair its index among those

    def residual(self, pair: mi.UInt32, t: mi.Float) -> mi.Float:
        """Interpolated ``R`` of ``pair`` at ray parameter ``t`` (the end values past the chord;
        0 for a pair without grid points, an invalid slot)."""
        points = dr.gather(mi.UInt32, self.points, pair)
        some = points >= GRID_MIN_POINTS
        last = dr.maximum(points, GRID_MIN_POINTS) - 1
        u = dr.clip((t - dr.gather(mi.Float, self.start, pair)) * dr.gather(mi.Float, self.inv_step, pair),
                    0.0, mi.Float(last))
        i = dr.minimum(mi.UInt32(u), last - 1)
        f = u - mi.Float(i)
        at = dr.gather(mi.UInt32, self.first, pair) + i
        inner, end = i > 0, i + 1 < last
        r0 = dr.gather(mi.Float, self.r, dr.select(inner, at - 1, at + 2), some)
        r1 = dr.gather(mi.Float, self.r, at, some)
        r2 = dr.gather(mi.Float, self.r, at + 1, some)
        r3 = dr.gather(mi.Float, self.r, dr.select(end, at + 2, at - 1), some)
        # quadratic extrapolation past the chord's ends (the cell's three grid points and the
        # one beyond them: a chord has at least GRID_MIN_POINTS), so quadratics stay exact
        r0, r3 = (dr.select(inner, r0, 3.0 * (r1 - r2) + r0), dr.select(end, r3, 3.0 * (r2 - r1) + r3))
        c1 = 0.5 * (r2 - r0)
        c2 = r0 - 2.5 * r1 + 2.0 * r2 - 0.5 * r3
        c3 = 0.5 * (r3 - r0) + 1.5 * (r1 - r2)
        return dr.fma(f, dr.fma(f, dr.fma(f, c3, c2), c1), r1)

    def box(self, pair: mi.UInt32, t: mi.Float) -> mi.Float:
        """The exact box SDF ``B`` of ``pair`` at ray parameter ``t``."""
        ol, dl, half = [dr.gather(type(x), x, pair) for x in self.views]
        return box_sdf_local(ol + t * dl, half)

    def sdf(self, pair: mi.UInt32, t: mi.Float) -> mi.Float:
        """``B`` exact plus the interpolated ``R`` of ``pair`` at ``t``."""
        return self.box(pair, t) + self.residual(pair, t)

    def sdf_within(self, pair: mi.UInt32, t: mi.Float, reach) -> tuple[mi.Float, mi.Float]:
        """:meth:`sdf` with ``R`` only where ``B <= reach`` (the rule of
        :meth:`~vsrd_plugins.sdf.InstanceField.lane_sdfs` with ``grad_reach``; elsewhere the
        value is ``B``, exact), and ``B``."""
        b = self.box(pair, t)
        return b + dr.select(b <= reach, self.residual(pair, t), 0.0), b



@dataclass(frozen=True)
class PairScan:
    """The instance SDF ``F = B + R`` of the valid (slot, ray) pairs for the detached scans of
    :func:`residual_minima` and
    :func:`~.extrema.snapped_positions` (pairs slot-major, as
    :class:`ChordGrid`'s). A slot beyond a ray's count of met boxes has nothing to scan: the
    scans run over the valid pairs alone (57 % of the pairs on the 6-box benchmark, 51-53 % at 3
    and 12 boxes), and their results read back as 0 there."""

    valid: mi.Bool  #: per pair: the slot holds one of the ray's boxes
    pairs: mi.UInt32  #: the valid pairs' indices
    rank: mi.UInt32  #: per pair its index among the valid ones
    at: Callable[[mi.UInt32, mi.Float], mi.Float]  #: ``F`` of given pairs at given ray parameters
    #: ``at`` can run inside a symbolic loop (arithmetic and gathers: the chord grid; not the
    #: residual MLP's batched evaluation, which compresses per instance), so iterative
    #: searches on it run as one kernel instead of one per step
    traceable: bool = False

    @staticmethod
    def of(valid: mi.Bool, at: Callable[[mi.UInt32, mi.Float], mi.Float], traceable: bool = False) -> "PairScan":
        pairs = dr.compress(valid)
        rank = dr.prefix_sum(mi.UInt32(valid))
        dr.eval(rank)
        return PairScan(valid, pairs, rank, at, traceable)

    def block_pairs(self, reps: int) -> tuple[mi.UInt32, mi.UInt32]:
        """Block index and pair of each lane of ``reps`` pair-major blocks of the valid pairs."""
        nv = dr.opaque(mi.UInt32, dr.width(self.pairs))
        q = dr.arange(mi.UInt32, reps * dr.width(self.pairs))
        block = q // nv
        return block, dr.gather(mi.UInt32, self.pairs, q - block * nv)

    def __call__(self, t: mi.Float, reps: int) -> mi.Float:
        """``F`` at ``t``: ``reps`` pair-major blocks of ray parameters of the valid pairs
        (evaluated; same layout)."""
        out = self.at(self.block_pairs(reps)[1], t)
        dr.eval(out)
        return out

    def spread(self, values: mi.Float, block: int) -> mi.Float:
        """Block ``block`` of :meth:`__call__`'s result per pair (0 at invalid pairs)."""
        at = self.rank + dr.opaque(mi.UInt32, block * dr.width(self.pairs))
        return dr.gather(mi.Float, values, at, self.valid)

    def full(self, t: mi.Float) -> mi.Float:
        """``F`` at one ray parameter per pair (every pair; 0 at invalid ones)."""
        return self.spread(self(dr.gather(mi.Float, t, self.pairs), 1), 0)



def slot_view(ctx: SamplingContext, views, kb: mi.UInt32) -> tuple:
    """Per ray the box-local ``(origin, direction, half)`` of instance ``kb`` (``views`` per
    instance; instance 0 where ``kb`` is no instance)."""
    out = list(views[0])
    for k in range(1, ctx.field.n):
        out = [dr.select(kb == k, v, o) for v, o in zip(views[k], out)]
    return tuple(out)


def pair_views(slot_views) -> tuple:
    """The box-local ray origins, directions and half sizes of every (slot, ray) pair,
    slot-major."""
    return tuple(concat([sv[i] for sv in slot_views]) for i in range(3))

def pair_sdf(ctx: SamplingContext, slot_views, slot_inst) -> Callable[[mi.UInt32, mi.Float], mi.Float]:
    """``at(pair, t)``: the instance SDF ``F = B + R`` of (slot, ray) pairs ``pair`` at ray
    parameters ``t`` (for :class:`PairScan`), detached and exact (``residual_grid = 0``;
    :class:`ChordGrid` interpolates ``R`` instead); invalid slots get their box's ``B``
    only."""
    flat = pair_views(slot_views)
    inst = concat(slot_inst)

    def at(pair: mi.UInt32, t: mi.Float) -> mi.Float:
        ol, dl, half = [dr.gather(type(x), x, pair) for x in flat]
        return box_sdf_local(ol + t * dl, half) + pair_residuals(ctx, flat, inst, pair, t)

    return at


def chord_grid(ctx: SamplingContext, dec, slot_views, slot_inst, count, picked: list[Picked]) -> "ChordGrid":
    """Exact residuals on a grid over each (slot, ray) pair's enlarged-box chord
    ``[entry, exit]``, spaced ``residual_grid / omega`` apart (at least
    :data:`GRID_MIN_POINTS` per chord), for :class:`ChordGrid` to interpolate (detached).

    ``R`` is smooth: a GELU MLP on a sinusoidal encoding whose highest frequency ``omega``
    is ``2^(F-1) pi`` times the input scale (4 rad/m by default), while ``B`` carries every
    kink of ``F = B + R`` along a ray. The searches for the extrema of ``F`` and the values
    that only decide which samples leave the AD graph need ``R`` at the resolution of its
    own features, not at every scan point of every cell: a long chord gets more points than
    a short one, about 35 per band on the integrator benchmark, where the scans evaluated
    ~90 and the values ~30 more.
    """
    spacing = ctx.settings.residual_grid / ctx.residual_omega()
    n_slots, n = len(slot_views), dr.width(count)
    a = concat([pk.entry for pk in picked])
    chord = dr.maximum(concat([pk.exit for pk in picked]) - a, 0.0)
    valid = concat([count > b for b in range(n_slots)])
    points = dr.select(valid, dr.maximum(mi.UInt32(dr.ceil(chord * (1.0 / spacing))) + 1, GRID_MIN_POINTS), 0)
    first = dr.prefix_sum(points)  # exclusive
    h = chord / mi.Float(dr.maximum(points, 2) - 1)
    inv_h = dr.select(h > 0.0, dr.rcp(dr.select(h > 0.0, h, 1.0)), 0.0)
    rank = dr.prefix_sum(mi.UInt32(points > 0))  # exclusive
    dr.eval(a, points, first, h, inv_h, rank)
    total = int(dr.sum(points)[0])
    # grid lane -> its pair: mark each pair's first lane, count the marks up to a lane
    busy = dr.compress(points > 0)
    mark = dr.zeros(mi.UInt32, total)
    dr.scatter(mark, 1, dr.gather(mi.UInt32, first, busy))
    pair = dr.gather(mi.UInt32, busy, dr.cumsum(mark) - 1)
    j = dr.arange(mi.UInt32, total) - dr.gather(mi.UInt32, first, pair)
    t_grid = dr.fma(dr.gather(mi.Float, h, pair), mi.Float(j), dr.gather(mi.Float, a, pair))
    flat, inst = pair_views(slot_views), concat(slot_inst)
    lattice = residual_lattice(ctx, dec, total)
    if lattice is None:
        r = pair_residuals(ctx, flat, inst, pair, t_grid)
    else:
        pl, ik = pair_points(flat, inst, pair, t_grid)
        r = lattice.residual(ik, pl)
    dr.eval(r)
    return ChordGrid(flat, a, inv_h, points, first, r, n, busy, rank)

def residual_lattice(ctx: SamplingContext, dec, grid_points: int) -> ResidualLattice | None:
    """The residual tabulated per instance (:class:`~vsrd_plugins.sdf.ResidualLattice`,
    spacing ``residual_lattice / omega``, over each box enlarged by the residual's reach)
    when that costs fewer MLP evaluations than ``grid_points`` chord-grid points do
    (counting a lookup as :data:`~vsrd_plugins.sdf.LATTICE_LOOKUP_COST` of one), else
    ``None``. A dense ray batch crosses each box many times and pays for the table once
    (6 boxes, 16k rays: 0.41M nodes instead of 1.24M grid points, chord grid 0.10 -> 0.06 s;
    12 boxes 0.16 -> 0.10 s); a sparse one is cheaper along its chords (at 4k rays and
    below on the integrator benchmark)."""
    if ctx.settings.residual_lattice <= 0:
        return None
    spacing = ctx.settings.residual_lattice / ctx.residual_omega()
    margin, half = dr.detach(ctx.residual_reach()), [dr.detach(h) for h in dec.half]
    dr.eval(margin, half)  # one kernel, then plain reads
    extents = np.stack([h.numpy() for h in half], axis=1) + float(margin[0])
    nodes = int(ResidualLattice.node_counts(extents, spacing).prod(axis=1).sum())
    if nodes >= grid_points * (1.0 - LATTICE_LOOKUP_COST):
        return None
    return ctx.field.residual.lattice(ctx.field.residual_weights(), extents, spacing)

def pair_points(flat, inst: mi.UInt32, pair: mi.UInt32, t: mi.Float) -> tuple[mi.Vector3f, mi.UInt32]:
    """Box-local point at ray parameter ``t`` and instance of each lane's (slot, ray)
    ``pair`` (``flat``, ``inst``: as for :func:`pair_residuals`)."""
    ol, dl = [dr.gather(type(x), x, pair) for x in flat[:2]]
    return ol + t * dl, dr.gather(mi.UInt32, inst, pair)

def pair_residuals(ctx: SamplingContext, flat, inst: mi.UInt32, pair: mi.UInt32, t: mi.Float) -> mi.Float:
    """Residual ``R`` of each lane's (slot, ray) ``pair`` at ray parameter ``t`` (detached;
    ``flat``: the pairs' box-local origins, directions and half sizes; ``inst``: the pairs'
    instances, ``num_instances`` for an invalid slot, whose ``R`` is 0), every instance in
    one batched evaluation."""
    pl, ik = pair_points(flat, inst, pair, t)
    dr.eval(pl, ik)
    groups = [(k, dr.compress(ik == k)) for k in range(ctx.field.n)]
    groups = [(k, idx) for k, idx in groups if dr.width(idx)]
    res = ctx.field.residual.evaluate_grouped(ctx.field.residual_weights(), [k for k, _ in groups],
                                               [dr.gather(mi.Vector3f, pl, idx) for _, idx in groups])
    out = dr.zeros(mi.Float, dr.width(t))
    for (_, idx), rk in zip(groups, res):
        dr.scatter(out, rk, idx)
        dr.eval(out)  # one kernel per instance: pending scatters of equal width share one
    return out


def kink_minima(sdf, kinks: list[mi.Float], bends: tuple[list[mi.Float], list[mi.Float]] = ([], []),
                 sharpest: float = 0.0) -> list[tuple[mi.Float, mi.Float, mi.Float]]:
    """Per (slot, ray) pair, slot-major: where ``F = B + R`` has a local minimum at a kink of
    ``B`` or beside a sharp bend of it, ``F`` there and, at a kink, the envelope weight of
    the face before it (from ``F``'s slopes on either side; ``-1`` beside a bend, where
    ``F`` is smooth), ascending, at most :data:`KINK_MINIMA` of them, ``-1`` past the last.

    ``kinks`` (ascending, ``-1`` for none; :func:`~vsrd_plugins.sdf.box_ray_kinks`):
    inside a box ``B`` along a ray is the max of its face planes, convex and piecewise
    linear, with a kink wherever the nearest face changes; ``R`` can make any kink a local
    minimum of ``F`` (the deepest point, or a face handing over to the exit face while the
    residual still falls). ``bends`` (the crossings and ``B`` there,
    :func:`~vsrd_plugins.sdf.box_ray_bends`): outside, a ray passing an edge within
    ``sharpest`` (the residual's own length scale) bends ``B`` as sharply as a kink over
    about ``B``'s width. A parabola through scan points on either side misses either by up
    to a cell. Each candidate is probed at five points ``KINK_PROBE`` apart (a bend: half
    its width, at least that) and is a minimum where the least probe is an inner one: a
    kink whose own value is least keeps its exact place, otherwise :data:`KINK_GOLDEN`
    golden-section steps between the least probe's neighbours find it (a parabola through
    the probes put the minimum beside a wide bend 2 cm off, beside the band's own sample
    at the closest approach, where it took a second sample for the same minimum)."""
    ts = list(kinks)
    widths = [dr.full(mi.Float, KINK_PROBE, dr.width(ts[0]))] * len(ts)
    exact = len(ts)
    for t, b in zip(*bends):
        # (a crossing on the surface, within rounding of it, is where the ray enters or leaves)
        ts.append(dr.select((b > KINK_PROBE) & (b < sharpest), t, -1.0))
        widths.append(dr.maximum(0.5 * b, KINK_PROBE))
    n_pairs = dr.width(ts[0])
    cand_t, cand_w = concat(ts), concat(widths)
    # the candidates, (candidate, pair) flat; padded lanes probe candidate 0 and write nothing
    live, real = compress_wide(cand_t >= 0.0)
    n_live = dr.width(live)
    found, value = dr.full(mi.Float, -1.0, dr.width(cand_t)), dr.zeros(mi.Float, dr.width(cand_t))
    weight = dr.full(mi.Float, -1.0, dr.width(cand_t))
    t_c, w_c = dr.gather(mi.Float, cand_t, live), dr.gather(mi.Float, cand_w, live)
    pair = live % dr.opaque(mi.UInt32, n_pairs)
    lane = dr.arange(mi.UInt32, 5 * n_live)
    c, j = lane // 5, lane % 5
    f = sdf.at(dr.gather(mi.UInt32, pair, c),
               dr.fma(dr.gather(mi.Float, w_c, c), mi.Float(j) - 2.0, dr.gather(mi.Float, t_c, c)))
    dr.eval(f)
    probes = [dr.gather(mi.Float, f, dr.arange(mi.UInt32, n_live) * 5 + j) for j in range(5)]
    best, arg = probes[0], mi.UInt32(0)
    for j in range(1, 5):
        better = probes[j] < best
        best, arg = dr.select(better, probes[j], best), dr.select(better, j, arg)
    inner = (arg >= 1) & (arg <= 3)
    f0 = pick(probes, dr.select(inner, arg, 1))  # pick is 1-based: probes arg - 1, arg, arg + 1
    f1 = pick(probes, arg + 1)
    f2 = pick(probes, dr.select(inner, arg + 2, 1))
    is_min = real & inner & (f1 < f0) & (f1 < f2)
    at_kink = (live < dr.opaque(mi.UInt32, exact * n_pairs)) & (arg == 2)
    dr.scatter(found, t_c, live, is_min)
    dr.scatter(value, f1, live, is_min)
    # at a kink the minimum's envelope weight of the face before it, from F's slopes on
    # either side (B's faces plus R's slope; see sdf.ridge_faces)
    dr.scatter(weight, envelope_weight((f1 - f0) / w_c, (f2 - f1) / w_c), live, is_min & at_kink)
    # elsewhere the minimum lies between the least probe's neighbours: golden section
    smooth, real = compress_wide(is_min & ~at_kink)
    tc, wc = dr.gather(mi.Float, t_c, smooth), dr.gather(mi.Float, w_c, smooth)
    ac = mi.Float(dr.gather(mi.UInt32, arg, smooth))
    pc = dr.gather(mi.UInt32, pair, smooth)

    t_min = golden_minimum(lambda t: sdf.at(pc, t), dr.fma(wc, ac - 3.0, tc), dr.fma(wc, ac - 1.0, tc),
                           KINK_GOLDEN, sdf.traceable, "vsrd_kink_golden")
    dr.scatter(found, t_min, dr.gather(mi.UInt32, live, smooth), real)
    dr.scatter(value, sdf.at(pc, t_min), dr.gather(mi.UInt32, live, smooth), real)
    cands, values, weights = ([block_of(x, c, n_pairs) for c in range(len(ts))] for x in (found, value, weight))
    out, low = [], mi.Float(-1.0)
    for _ in range(KINK_MINIMA):  # the least minima in order
        nxt, f_nxt, w_nxt = mi.Float(dr.inf), mi.Float(0.0), mi.Float(-1.0)
        for t, f, lam in zip(cands, values, weights):
            take = (t > low) & (t < nxt)
            nxt, f_nxt, w_nxt = dr.select(take, t, nxt), dr.select(take, f, f_nxt), dr.select(take, lam, w_nxt)
        low = dr.select(dr.isfinite(nxt), nxt, low)
        out.append((dr.select(dr.isfinite(nxt), nxt, -1.0), f_nxt, w_nxt))
    dr.eval(out)
    return out


def residual_peaks(sdf, peaks: list[GapPeak], slot_ts: list[mi.Float], reach) -> list[GapPeak]:
    """The gap peaks of :func:`~.bands.gap_peaks` (found on the boxes' ``B``) moved to where the
    instance SDFs ``F = B + R`` of their two crossing slots cross (detached; ``sdf``: the
    :class:`PairScan` of the pairs), with the envelope weight from ``F``'s slopes there.

    ``R >= 0`` moves the crossing by up to its own size, and the descent into the next box
    telescopes from the scene SDF's peak: on the box peak a ray's labels were off by up to
    0.011 (random 2-3-box scenes). ``F_a - F_a'`` rises through the gap (``a`` rising, ``a'``
    falling), so :data:`PEAK_STEPS` regula falsi steps between the two slots' deepest
    points find the crossing; a gap where it does not change sign keeps the box peak."""
    n, gaps = dr.width(slot_ts[0]), len(peaks) - 1
    if gaps == 0:
        return peaks
    no = dr.opaque(mi.UInt32, n)  # opaque: n changes every call
    # every gap of every ray in one batch, (gap, ray) flat; the gaps that exist only
    flat = [concat([getattr(pk, name) for pk in peaks[:-1]]) for name in ("t", "ok", "lam", "a", "b")]
    lo = concat([slot_ts[b] for b in range(gaps)])
    hi = dr.maximum(concat([slot_ts[b + 1] for b in range(gaps)]), lo)
    # beyond the reach of both boxes the SDFs there are the boxes' (the residual is only
    # added within it, see InstanceField.lane_sdfs): the box peak is the crossing
    idx, real = compress_wide(flat[1] & (concat([pk.f for pk in peaks[:-1]]) <= reach))
    ray = idx % no
    pa = mi.UInt32(dr.gather(mi.Float, flat[3], idx)) * no + ray
    pb = mi.UInt32(dr.gather(mi.Float, flat[4], idx)) * no + ray

    def gap(t):  # F_a - F_a' at one t per lane (one kernel on the chord grid)
        return sdf.at(pa, t) - sdf.at(pb, t)

    lo, hi = dr.gather(mi.Float, lo, idx), dr.gather(mi.Float, hi, idx)
    g_lo, g_hi = gap(lo), gap(hi)
    ok = real & (g_lo < 0.0) & (g_hi > 0.0)
    t = illinois_root(gap, lo, hi, g_lo, g_hi, PEAK_STEPS, sdf.traceable, "vsrd_residual_peaks")
    # slopes of F_a, F_a' along the ray at the crossing (central differences)
    slope = [(sdf.at(p, t + KINK_PROBE) - sdf.at(p, t - KINK_PROBE)) * (0.5 / KINK_PROBE) for p in (pa, pb)]
    crossing = (slope[0] > 0.0) & (slope[1] < 0.0)
    lam = dr.select(crossing, envelope_weight(dr.select(crossing, slope[0], 1.0),
                                              dr.select(crossing, slope[1], -1.0)), -1.0)
    dr.scatter(flat[0], t, idx, ok)
    dr.scatter(flat[2], lam, idx, ok)
    dr.eval(flat[0], flat[2])
    return [pk._replace(t=block_of(flat[0], b, n), lam=block_of(flat[2], b, n))
            for b, pk in enumerate(peaks[:-1])] + peaks[-1:]


def residual_minima(ctx: SamplingContext, sdf, slot_views, count, picked: list[Picked]) -> list[mi.Float]:
    """Per slot, where the instance SDF ``F = B + R`` is least along the ray (detached;
    ``sdf``: the :class:`PairScan` of the pairs).

    ``R >= 0`` moves ``F``'s minimum off the box's: along a ray grazing a face ``B`` is
    nearly flat and ``R`` decides, and inside a box ``F`` can keep falling past ``B``'s
    deepest point. The telescoping integral needs that minimum as a sample (labels were off
    by p99 0.025 with the box's, 6 boxes at s = 10). ``F`` is not convex, so the search
    scans ``residual_scan`` points of a window (the chord ``[entry, exit]`` of a box the
    ray enters, ``[t* - w, t* + w]`` around the box's closest approach otherwise), keeps the
    least of them and the box's own minimum ``t*``: one batched evaluation of ``F`` (every slot
    and instance together), outside the AD graph.
    """
    cfg = ctx.settings
    n_slots, n = len(slot_views), dr.width(count)
    w = ctx.band_half_width()
    a_s, b_s, ts_s = [], [], []
    for pk in picked:
        a_s.append(dr.select(pk.hit, pk.centre, dr.maximum(pk.tstar - w, pk.entry)))
        b_s.append(dr.select(pk.hit, dr.maximum(pk.surface_exit, pk.centre), dr.minimum(pk.tstar + w, pk.exit)))
        ts_s.append(pk.tstar)
    a, b, ts = concat(a_s), concat(b_s), concat(ts_s)
    k = cfg.residual_scan
    step = (b - a) / (k - 1)
    # candidates: k uniform points of [a, b], then t*; per valid pair, in one expression
    block, pair = sdf.block_pairs(k + 1)
    cand = dr.select(block == k, dr.gather(mi.Float, ts, pair),
                     dr.fma(dr.gather(mi.Float, step, pair), mi.Float(block), dr.gather(mi.Float, a, pair)))
    values = sdf(cand, k + 1)
    width = n_slots * n
    best_v = dr.full(mi.Float, 1e30, width)
    best_i = dr.zeros(mi.UInt32, width)
    for i in range(k + 1):
        v = sdf.spread(values, i)
        better = v < best_v
        best_v, best_i = dr.select(better, v, best_v), dr.select(better, i, best_i)
    t_min = dr.select(best_i == k, ts, dr.fma(step, mi.Float(best_i), a))
    return [block_of(t_min, b_, n) for b_ in range(n_slots)]
