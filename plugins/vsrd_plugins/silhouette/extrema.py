"""Samples at the extrema of ``B + R``: moved band and tail samples, and an isolated band's extrema.

The discrete opacity telescopes over each monotone run of the scene SDF: the integral is right
where the samples sit on the run ends, whatever lies between. With the residual field a ray
that runs close to a face sees several shallow minima and maxima of ``F = B + R``; the moved
samples (:func:`snapped_positions`) take them, and an isolated ray's band
(:func:`extremum_samples`) is made of them.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..common import block_of, compress_wide, concat, golden_minimum, golden_section, pick, sorted_arrays
from .residual_search import GRID_MIN_POINTS, KINK_GOLDEN, KINK_PROBE, ChordGrid, PairScan
from .settings import SamplingContext, halves
from .slots import ISOLATED_ANCHORS, Slot, band_layout, sub_sample

#: Moved samples (:func:`snapped_positions`): a local extremum of the scan of ``B + R`` claims
#: a sample only where it differs from a neighbouring scan point by more than this (m; above the
#: chord grid's interpolation wiggles on flat stretches).
SNAP_PROMINENCE = 2e-4
#: Golden-section steps that place a moved sample's extremum between the scan points around it
#: (:func:`refined_extrema`): the bracket of two scan intervals shrinks 47x, to a few millimetres.
SNAP_GOLDEN = 8
#: Scan points per chord-grid cell of :func:`chord_extrema`.
EXTREMUM_SCAN = 2


def snapped_slots(ctx: SamplingContext, sdf, slots: list[Slot], minima: list[tuple]) -> list[list[list[mi.Float]]]:
    """Moved positions of every slot's samples in the order :func:`~.layout.sub_bands` reads them: the first
    tail's ``kp`` in ``(hi, extra)``, the second tail's ``kq`` in ``(extra, tail end]``, the
    band's first half's ``K/2 - 1`` in ``(lo, mid)`` (its last sample, the centre, stays)
    and its second half's ``K/2 - 1`` in ``(mid, hi)`` (its last sample stays too: where a
    hit band ends at its least ``B + R``, that is ``hi``, and a maximum just before it took
    the sample when it could move: trained fields, labels off by 0.05); per part a list (slot) of lists
    (sample) of arrays (ray). ``minima``: the minima of each (slot, ray) pair's ``F`` at
    the kinks and bends of its ``B`` (:func:`~.residual_search.kink_minima`)."""
    kp, kq = ctx.tail_samples()
    k1, k2 = halves(ctx.settings.band_samples)
    lo, mid, hi, extra, tail = ([getattr(sl, name) for sl in slots]
                                for name in ("lo", "mid", "hi", "extra", "tail_end"))
    empty = [[] for _ in slots]
    scan = ctx.settings.residual_tail_scan
    return [snapped_positions(sdf, hi, extra, kp + 1, kp, scan, kinks=minima) if kp else empty,
            snapped_positions(sdf, extra, tail, kq, kq, scan, kinks=minima),
            snapped_positions(sdf, lo, mid, k1, k1 - 1, scan, True, kinks=minima) if k1 > 1 else empty,
            snapped_positions(sdf, mid, hi, k2, k2 - 1, scan, kinks=minima) if k2 > 1 else empty]


def snapped_positions(sdf: PairScan, starts: list[mi.Float], ends: list[mi.Float], k_sub: int, k: int, scan: int,
                      dense_at_b: bool = False, kinks: list[tuple[mi.Float, ...]] = ()) -> list[list[mi.Float]]:
    """Per slot the positions of the first ``k`` samples of the sub-band ``(starts[b],
    ends[b]]`` of ``k_sub`` samples (:func:`~.slots.sub_sample`), moved to the local extrema of
    ``F = B + R`` (detached; ``sdf``: the :class:`PairScan` of the pairs).

    Along a ray that runs close to a face, ``B + R`` has several shallow local minima and
    maxima, and the discrete opacity telescopes over each monotone run: it is right where
    the samples sit on those extrema, whatever lies between. Uniform samples straddle them
    (integrator benchmark's 12-box residual scene: labels max 0.0227 with 12 tail samples,
    0.0117 with 32; moved, 3 scan points per sample: 0.0055 with 12). Sample ``i``
    owns the cell between its nominal position and its predecessor's
    (:func:`~.slots.sub_sample`); ``residual_tail_scan`` points per cell (the last at the nominal
    position) are scanned, over the cells of the ``k`` moved samples and, where ``k <
    k_sub``, the fixed next sample's. Every scan point that is a local extremum of the scan
    (by more than :data:`SNAP_PROMINENCE`) places a sample between its two neighbours
    (:func:`refined_extrema`: golden-section steps; the vertex of the parabola through
    the three missed the extrema of trained residual fields by up to 0.14 m); ``kinks`` (per pair, ascending, with ``F`` there,
    :func:`~.residual_search.kink_minima`), the minima of ``F`` at kinks and sharp bends of ``B``, place one
    each exactly (a search across a kink misses it by up to a cell), as the event of the
    scan point before it where that has no extremum, else of the one after it (a second
    kink in one scan interval goes without), and the scan sees them as points of its own: an extremum
    test next to a kink compares with the kink's value (the scan point beyond it can hide a
    maximum before the kink, or show a minimum that is the kink's).
    Taken in order along the ray, the ``j``-th of the ``q`` extrema takes the first sample
    after the last one taken: its own cell's, or an earlier one where its own would leave
    fewer than ``q - j`` samples for the extrema after it, or a later one where its own is
    taken; the samples no extremum took keep their nominal places, clipped between the
    taken ones around them, so the samples stay sorted (the tails do, and the rank merge of
    :func:`~.layout.adaptive_groups` holds). Random 2-3-box scenes (256 rays, seeds 40-299): scenes
    with a label above 0.01 19 -> 9 of 260, worst 0.039 -> 0.019, against one sample per
    cell that took its cell's largest extremum and lent its runner-up to a free neighbour
    (which left a cell with two extrema, a cell holding the deepest point, or extrema
    crowding one end of a sub-band with one sample short); with the kinks, bends and
    residual peaks none of the 260 (``docs/integrators.md``, "What each feature buys").
    """
    per = scan
    n_slots, n = len(starts), dr.width(starts[0])
    a, b = concat(starts), concat(ends)
    # the cells of the k moved samples, and the fixed next sample's (k < k_sub): an extremum
    # there takes the last moved sample where it is free
    cells = k + 1 if k < k_sub else k
    nominal = [sub_sample(a, b, i, k_sub, dense_at_b) for i in range(cells + 1)]

    def scan_point(lo, hi, j):
        """``j``-th of ``per`` points of the cell ``(lo, hi]`` (the last at ``hi`` exactly)."""
        return dr.select(j == per, hi, dr.fma(hi - lo, mi.Float(j) * (1.0 / per), lo))

    # scan parameters: the start, ``per`` per cell (the last at its nominal sample), and the
    # next nominal sample (a fixed one: a band's centre, a tail's extra sample) or none
    ts = [nominal[0]]
    for i in range(1, cells + 1):
        ts += [scan_point(nominal[i - 1], nominal[i], j) for j in range(1, per + 1)]
    # the same parameters as one flat array, pair-major blocks of the valid pairs, from one
    # expression
    m, pair = sdf.block_pairs(len(ts))
    ap, bp = dr.gather(mi.Float, a, pair), dr.gather(mi.Float, b, pair)
    cell = dr.select(m == 0, 0, (m + per - 1) // per)
    j = dr.select(m == 0, per, m - (cell - 1) * per)
    flat = scan_point(sub_sample(ap, bp, dr.select(cell > 0, cell - 1, 0), k_sub, dense_at_b),
                      sub_sample(ap, bp, cell, k_sub, dense_at_b), j)
    values = sdf(flat, len(ts))
    v = [sdf.spread(values, i) for i in range(len(ts))]
    # the local extrema of the scan and the kinks of B where F has a local minimum (see
    # residual_search.kink_minima; exact, where a search between the scan points on either side would miss them), in
    # order along the ray: the j-th of q takes the first sample after the last one taken,
    # at its own cell's unless that would leave too few samples for the q - j after it.
    # A kink on the fixed samples around the cells (the deepest point, a band's centre)
    # has one already
    pending = [(kt > a + KINK_PROBE) & (kt < nominal[cells] - KINK_PROBE) for kt, *_ in kinks]

    def kink_in(x0, x1):
        """The first pending kink in the scan interval ``(x0, x1]`` (its place), and whether
        there is one (a second one there goes without)."""
        here, at = mi.Bool(False), x1
        for pend, (kt, *_) in reversed(list(zip(pending, kinks))):
            inside = pend & (x0 < kt) & (kt <= x1)
            here, at = here | inside, dr.select(inside, kt, at)
        return here, at

    events = []  # per scan point: (event, place, cell, bracket low, bracket high, sign)
    for m in range(1, len(ts)):
        x0, x1 = ts[m - 1], ts[m]
        cell = mi.UInt32(min((m + per - 1) // per, k))
        # a kink in the interval ending at scan point m takes the event of the scan point
        # before it where that has no extremum, else m's (an extremum at m then goes
        # without: three features within two scan intervals)
        event, at = kink_in(x0, x1)
        # sign: 1 a maximum, -1 a minimum, 0 a kink (placed exactly)
        sign, b_lo, b_hi = mi.Int32(0), x0, x1
        if m > 1:
            prev_event, prev_at, prev_cell, prev_lo, prev_hi, prev_sign = events[-1]
            to_prev = event & ~prev_event
            events[-1] = (prev_event | to_prev, dr.select(to_prev, at, prev_at), prev_cell, prev_lo, prev_hi,
                          dr.select(to_prev, 0, prev_sign))
            event &= ~to_prev
        if m < len(ts) - 1:
            x2 = ts[m + 1]
            f0, f1, f2 = v[m - 1], v[m], v[m + 1]
            # the nearest kink on either side between the scan points stands in for them
            for pend, (kt, kf, *_) in zip(pending, kinks):
                left = pend & (x0 < kt) & (kt < x1)
                x0, f0 = dr.select(left, kt, x0), dr.select(left, kf, f0)
            for pend, (kt, kf, *_) in reversed(list(zip(pending, kinks))):
                right = pend & (x1 < kt) & (kt < x2)
                x2, f2 = dr.select(right, kt, x2), dr.select(right, kf, f2)
            extremum = ((f1 > f0) & (f1 >= f2)) | ((f1 < f0) & (f1 <= f2))
            extremum &= dr.maximum(dr.abs(f1 - f0), dr.abs(f1 - f2)) > SNAP_PROMINENCE
            # placed between x0 and x2 once taken (refined_extrema)
            sign = dr.select(extremum & ~event, dr.select(f1 > f0, 1, -1), sign)
            b_lo, b_hi = x0, x2
            event |= extremum
        events.append((event, at, cell, b_lo, b_hi, sign))
    q = mi.UInt32(0)
    for event, *_ in events:
        q += dr.select(event, 1, 0)
    pos = list(nominal[1:k + 1])
    taken = [mi.Bool(False) for _ in range(k)]
    # per sample the bracket and sign of the extremum that took it (sign 0: none, a kink)
    brackets = [(mi.Float(0.0), mi.Float(0.0), mi.Int32(0)) for _ in range(k)]
    last, j = mi.UInt32(0), mi.UInt32(0)  # the last sample taken (1-based; 0: none), events
    for event, at, cell, b_lo, b_hi, sign in events:
        j = j + dr.select(event, 1, 0)
        slot = dr.maximum(last + 1, dr.minimum(cell, (k + j) - dr.minimum(q, k + j)))
        take = event & (slot <= k)
        for i in range(1, k + 1):
            here = take & (slot == i)
            pos[i - 1] = dr.select(here, at, pos[i - 1])
            brackets[i - 1] = tuple(dr.select(here, new, old) for new, old in zip((b_lo, b_hi, sign), brackets[i - 1]))
            taken[i - 1] |= here
        last = dr.select(take, slot, last)
    pos = refined_extrema(sdf, pos, brackets)
    # the samples no extremum took keep their nominal places, clipped between the taken
    # ones around them: the samples stay sorted
    low = mi.Float(-dr.inf)
    for i in range(k):
        pos[i] = dr.maximum(pos[i], low) if i else pos[i]
        low = dr.select(taken[i], pos[i], low)
    high = mi.Float(dr.inf)
    for i in reversed(range(k)):
        pos[i] = dr.minimum(pos[i], high)
        high = dr.select(taken[i], pos[i], high)
    # every moved position in one kernel (the per-slot gathers below would evaluate each
    # alone, re-reading the scan values once per position)
    dr.eval(pos)
    return [[block_of(p, s_, n) for p in pos] for s_ in range(n_slots)]

def refined_extrema(sdf, pos: list[mi.Float], brackets: list[tuple]) -> list[mi.Float]:
    """``pos`` (per moved sample, per pair) with the samples that a scanned extremum took
    (``brackets[i] = (low, high, sign)``, sign 1: a maximum, -1: a minimum, 0: none or a
    kink) moved to it by :data:`SNAP_GOLDEN` golden-section steps between the scan points
    around it, on ``F`` (``sdf``: the :class:`PairScan`). One search over the taken samples
    of the valid pairs only: the untaken ones, most of them on an untrained field, cost
    nothing."""
    width, n_pos = dr.width(pos[0]), len(pos)
    dr.eval(pos, brackets)  # one kernel of the scan (a gather evaluates its source alone)
    # every (sample, pair) as one lane, sample-major: the positions, brackets and signs
    # gathered in one kernel (concatenating them array by array launched a kernel per array
    # and re-ran the scan's expression for each)
    lane = dr.arange(mi.UInt32, n_pos * width)
    which = lane // dr.opaque(mi.UInt32, width)
    pair = lane - which * dr.opaque(mi.UInt32, width)

    def flat_of(arrays, ty=mi.Float):
        return pick([dr.gather(ty, a, pair) for a in arrays], which + 1)

    flat = flat_of(pos)
    lo, hi = (flat_of([b[a] for b in brackets]) for a in range(2))
    sign = flat_of([b[2] for b in brackets], mi.Int32)
    candidate = (sign != 0) & dr.gather(mi.Bool, sdf.valid, pair)
    dr.eval(flat, lo, hi, sign, candidate)
    # padded (compress_wide): the same kernels however many samples were taken, none included
    lanes, real = compress_wide(candidate)
    at_pair = dr.gather(mi.UInt32, pair, lanes)
    sg = dr.gather(mi.Int32, sign, lanes)

    def f(t):
        value = sdf.at(at_pair, t)
        return dr.select(sg == 1, -value, value)

    refined = golden_minimum(f, dr.gather(mi.Float, lo, lanes), dr.gather(mi.Float, hi, lanes), SNAP_GOLDEN,
                             sdf.traceable, "vsrd_snap_refine")
    dr.scatter(flat, refined, lanes, real)
    return [block_of(flat, i, width) for i in range(n_pos)]


def worth_isolating(ctx: SamplingContext, isolated: mi.Bool, count: mi.UInt32, n_slots: int) -> tuple[mi.Bool, bool]:
    """With the residual field, ``isolated`` where the batch's isolated rays together pay for
    their sample groups, else no ray, and which of the two: a group costs a fixed
    ``isolated_group_cost`` on top of its samples, and an isolated band saves the full
    layout's samples minus its own (:func:`extremum_samples`). (6 boxes, 1000 rays: 10 %
    slower with the isolated rays in groups of their own; 16k rays 25 % faster.) Decided
    for the batch as a whole, not per band count: a band count whose isolated group came
    and went from step to step compiled its kernels at the first step it came.
    """
    saved_per_band = band_layout(ctx, False, ctx.settings.band_samples)[1] - band_layout(ctx, True)[1]
    hist = dr.zeros(mi.UInt32, n_slots + 1)
    dr.scatter_add(hist, mi.UInt32(isolated), count)
    rays = hist.numpy()[1:].astype(np.int64)
    saved = int((rays * np.arange(1, n_slots + 1)).sum()) * saved_per_band
    worth = saved >= ctx.settings.isolated_group_cost * int((rays > 0).sum()) and saved > 0
    return (isolated if worth else dr.zeros(mi.Bool, dr.width(count))), worth


def extremum_samples(sl: Slot, extrema: list[mi.Float]) -> tuple:
    """An isolated ray's samples of a band after its entry, with the residual field: its
    anchors (:data:`ISOLATED_ANCHORS`), the extrema of ``B + R`` along the chord
    (:func:`chord_extrema`; ``-1``: none) and its minima at kinks and bends of ``B``
    (:attr:`Slot.kinks`, :func:`~.residual_search.kink_minima`; :data:`KINK_MINIMA` of them), sorted (the
    exit stands in for missing ones).

    On an isolated ray every other box is beyond its culling margin at the band's samples,
    so the labels are the band's opacity, which telescopes over each monotone run of ``F =
    B + R``: it depends on ``F`` at the run ends alone. Those are the chord's ends, the least
    ``F`` and the extrema, which these samples hold.
    """
    kink_ts = list(sl.kinks[0::2])
    return tuple(sorted_arrays([*(getattr(sl, name) for name in ISOLATED_ANCHORS),
                                *(dr.select(x >= 0.0, x, sl.tail_end) for x in (*extrema, *kink_ts))]))


def chord_extrema(ctx: SamplingContext, grid: ChordGrid, scan: mi.Bool,
                  kinks: list[mi.Float]) -> tuple[list[mi.Float], mi.UInt32]:
    """Per (slot, ray) pair of ``grid`` where ``scan`` holds: the first ``isolated_extrema``
    local extrema of ``F = B + R`` along its chord (``-1`` past the last) and how many there
    are (detached; 0 and ``-1`` elsewhere). ``kinks``: per pair the minima of ``F`` at kinks
    of ``B`` (ascending, ``-1`` for none; :func:`~.residual_search.kink_minima`).

    ``F`` (``B`` exact, ``R`` interpolated, :class:`ChordGrid`) is scanned at
    :data:`EXTREMUM_SCAN` points per grid cell and at the kinks, in order; an extremum
    counts once ``F`` has moved away from it by :data:`SNAP_PROMINENCE` (hysteresis: a flat
    extremum counts as well as a sharp one, the chord grid's wiggles do not), and
    :data:`KINK_GOLDEN` golden-section steps between the scan points around it place it.
    The moved samples of the full layout (:func:`snapped_positions`) take an extremum only
    where it differs from a neighbouring scan point by the prominence: a flat maximum
    between two minima went unseen there and was covered by the band's other samples, which
    an isolated band does not have (labels off by 0.009 on the integrator benchmark's 6-box
    scene). Without the kinks among the scan points, a maximum 8 cm past a kink minimum
    went unseen between the scan points on either side (12 boxes, 16k rays: one ray's label
    off by 0.0087).
    """
    n_ext = ctx.settings.isolated_extrema
    width = dr.width(grid.points)
    lanes = dr.compress(scan & (grid.points >= GRID_MIN_POINTS))
    extrema = [dr.full(mi.Float, -1.0, width) for _ in range(n_ext)]
    found = dr.zeros(mi.UInt32, width)
    if dr.width(lanes) == 0:
        return extrema, found
    start = dr.gather(mi.Float, grid.start, lanes)
    h = dr.rcp(dr.gather(mi.Float, grid.inv_step, lanes) * EXTREMUM_SCAN)
    last = (dr.gather(mi.UInt32, grid.points, lanes) - 1) * EXTREMUM_SCAN
    # the kinks inside the chord, ascending, +inf past the last
    ks = [dr.gather(mi.Float, kt, lanes) for kt in kinks]
    end = dr.fma(mi.Float(last), h, start)
    ks = [dr.select((kt > start) & (kt < end), kt, dr.inf) for kt in ks] + [mi.Float(dr.inf)]

    def f(x):
        return grid.sdf(lanes, x)

    def next_kink(j):
        return pick(ks, dr.minimum(j, len(ks) - 1) + 1)

    prom = mi.Float(SNAP_PROMINENCE)
    # direction: 0 undecided (the chord's start is a sample anyway), 1 rising, -1 falling;
    # (f, x) of the running extremum in that direction; per extremum its place and sign
    state = (mi.UInt32(1), mi.UInt32(0), mi.Int32(0), f(start), start, mi.UInt32(0),
             *[mi.Float(-1.0) for _ in range(n_ext)], *[mi.Int32(0) for _ in range(n_ext)])

    def body(i, j, direction, run_f, run_x, count, *ext):
        places, signs = list(ext[:n_ext]), list(ext[n_ext:])
        # the next scan point: the next kink where it comes before the next grid point
        x_grid = dr.fma(mi.Float(i), h, start)
        x_kink = next_kink(j)
        at_kink = x_kink <= x_grid
        x = dr.select(at_kink, x_kink, x_grid)
        fi = f(x)
        # undecided: the first move by the prominence sets the direction
        undecided = direction == 0
        rises, falls = undecided & (fi > run_f + prom), undecided & (fi < run_f - prom)
        # a running maximum (rising) or minimum (falling) confirmed by a return past it
        confirmed = ((direction == 1) & (fi < run_f - prom)) | ((direction == -1) & (fi > run_f + prom))
        places = [dr.select(confirmed & (count == e), run_x, v) for e, v in enumerate(places)]
        signs = [dr.select(confirmed & (count == e), direction, v) for e, v in enumerate(signs)]
        count = count + dr.select(confirmed, 1, 0)
        direction = dr.select(rises | (confirmed & (direction == -1)), 1,
                              dr.select(falls | (confirmed & (direction == 1)), -1, direction))
        better = ((direction == 1) & (fi > run_f)) | ((direction == -1) & (fi < run_f))
        restart = rises | falls | confirmed | better
        return (dr.select(at_kink, i, i + 1), dr.select(at_kink, j + 1, j), direction,
                dr.select(restart, fi, run_f), dr.select(restart, x, run_x), count, *places, *signs)

    state = dr.while_loop(state, lambda i, j, *s: (i <= last) | (next_kink(j) < dr.inf), body,
                          label="vsrd_chord_extrema")
    count, places, signs = state[5], state[6:6 + n_ext], state[6 + n_ext:]
    # between the scan points on either side: the least F for a minimum, the least -F for
    # a maximum (sign 1: the scan was rising into it)
    fs = [(lambda t, sg=sg: dr.select(sg == 1, -f(t), f(t))) for sg in signs]
    refined = golden_section(fs, [(x - h, x + h) for x in places], KINK_GOLDEN, "vsrd_chord_extrema_refine")
    for e, (x, xr) in enumerate(zip(places, refined)):
        dr.scatter(extrema[e], dr.select(x >= 0.0, xr, -1.0), lanes)
    dr.scatter(found, count, lanes)
    dr.eval(extrema, found)
    return extrema, found
