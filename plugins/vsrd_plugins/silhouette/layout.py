"""The adaptive sampler's sample layout: every ray's band samples, merged in order by rank.

Rays with the same band count and layout form a :class:`~.slots.SampleGroup`: ``m`` samples per
ray, each band's samples computed from its :class:`~.slots.Slot` anchors and merged by rank (a
sample's index in its band plus, per other band, how many of that band's samples come before
it: a binary search, as bands are internally sorted), so no per-ray sort is needed.
"""

from __future__ import annotations

from typing import Iterator

import drjit as dr
import mitsuba as mi

from ..common import compress_wide, count_prefix, pick
from .bands import Bands
from .residual_search import KINK_PROBE
from .settings import SamplingContext, halves
from .slots import SampleGroup, Slot, band_layout, count_before, sub_sample


def sub_bands(sl: Slot, kk: int, kp: int, kq: int, snapped: bool, extrema: bool = False) -> list[tuple]:
    """A band's runs of samples between its entry and its extra sample and after it (see
    :func:`adaptive_groups`), as ``(first index in the band, count, value(i), counter(before))``:
    ``value`` gives the ``i``-th (1-based) sample, ``counter`` how many of them satisfy
    ``before`` (a prefix). From :func:`~.slots.sub_sample`'s formula, or from the positions
    :func:`~.extrema.snapped_slots` moved (``snapped``; :attr:`Slot.moved`), or, for an isolated
    ray with the residual field (``extrema``), one run of every sample after the entry
    (:attr:`Slot.isolated`)."""
    lo, mid, hi, ex = sl.lo, sl.mid, sl.hi, sl.extra
    k1, k2 = halves(kk)
    out = []

    def formula(first, k_run, a, b, k_sub, dense_at_b=False):
        out.append((first, k_run, lambda i: sub_sample(a, b, i, k_sub, dense_at_b),
                    lambda before: count_before(a, b, k_sub, before, dense_at_b, n=k_run)))

    def data(first, values):
        out.append((first, len(values), lambda i: pick(values, i), lambda before: count_prefix(len(values), lambda i: pick(values, i), before)))

    if extrema:
        data(1, list(sl.isolated))
        return out
    moved = list(sl.moved)
    tail1, moved = moved[:kp], moved[kp:]
    tail2, moved = moved[:kq], moved[kq:]
    band1, band2 = moved[:k1 - 1], moved[k1 - 1:k1 - 2 + k2]
    if snapped:
        data(1, band1 + [mid])
        if k2:
            data(k1 + 1, band2 + [hi])
        if kp:
            data(kk + 1, tail1)
        if kq:
            data(kk + kp + 2, tail2)
    else:
        formula(1, k1, lo, mid, k1, True)
        if k2:
            formula(k1 + 1, k2, mid, hi, k2)
        if kp:  # strictly inside (hi, ex): the extra sample follows
            formula(kk + 1, kp, hi, ex, kp + 1)
        if kq:
            formula(kk + kp + 2, kq, ex, sl.tail_end, kq)
    return out


def adaptive_groups(ctx: SamplingContext, bands: Bands) -> Iterator[SampleGroup]:
    """Sample positions for the adaptive strategy, one group per band count and layout
    (isolated rays, :func:`~.bands.isolated_rays`, get ``isolated_band_samples`` instead of ``K``).

    Yields a :class:`SampleGroup` ``(rays, t, m, active, inst, deepest, peak, own)``: rays with exactly ``g`` bands get
    ``m = g (K + 3 + T)`` samples (entry, ``K`` band samples, the first tail, closest approach /
    exit, the second tail, and the scene SDF's peak before the next band, per band; ``T`` tail
    samples only with the residual search, :meth:`~.settings.SamplingContext.tail_samples`), merged in order by rank: a
    sample's index in its band plus, per other band, how many of that band's samples come
    before it (a binary search: bands are internally sorted), so no per-ray sort is needed.
    ``active`` masks the padding copy of a single-ray group; ``inst`` holds the ``g`` band instances of
    each ray (the only instances evaluated at its samples); ``deepest`` is, per sample, the band
    whose box's deepest point along the ray this sample is (``g`` for none); ``peak`` per sample
    the two bands whose boxes cross there and the envelope weight of the first if it is a gap
    peak (else ``-1``); ``own`` per sample its band in an isolated group (``None`` otherwise).
    """
    kp, kq = ctx.tail_samples()
    ray_idx, count, slots, slot_inst, slot_hit, isolated = (bands.rays, bands.count, bands.slots, bands.inst,
                                                            bands.hit, bands.isolated)
    if not slots:
        return
    # samples moved to the extrema of B + R (:func:`~.extrema.snapped_slots`) are data, not
    # formulas: :attr:`Slot.moved` holds them (the full-band layout only)
    moved = ctx.snaps()
    # (isolated rays?, K): rays of isolated bands get their own groups with fewer samples
    layouts = [(False, ctx.settings.band_samples)]
    if ctx.isolates():
        layouts.append((True, ctx.settings.isolated_band_samples))
    for g, (iso, kk) in ((g, lay) for g in range(1, len(slots) + 1) for lay in layouts):
        # with the residual field an isolated band is its entry, the samples of
        # Slot.isolated and the gap peak (the extra sample among them)
        extrema = iso and moved
        j_ex, per = band_layout(ctx, extrema, kk)
        with dr.suspend_grad():
            # two padding rays (copies, masked out by ``active``) in every group: a width-1
            # group would turn its values into kernel literals (new kernels for every value,
            # e.g. each sharpness), and padding only those compiled other kernels for them
            sub, active = compress_wide((count == g) & (isolated == iso))
            na = dr.width(sub)
            real = na - 2
            if real == 0:
                continue
            m = g * per
            lane = dr.arange(mi.UInt32, na * m)
            r = lane // m
            q = lane % m
            band = q // per
            j = q % per
            rows = dr.gather(mi.UInt32, sub, r)
            sl = [slots[b].map(lambda v: dr.gather(mi.Float, v, rows)) for b in range(g)]
            # this lane's own sample value: entry, K/2 samples in (lo, mid], K/2 in (mid, hi],
            # the first tail in (hi, extra), extra, the second tail in (extra, tail end], and
            # the gap peak after the band (its own one-sample group in the merge)
            is_peak = j == per - 1
            # per band its sub-bands: (first index, samples, values) with values a formula of
            # the 1-based index or the moved positions (see extrema.snapped_slots)
            snap = moved and not iso
            parts = [sub_bands(sl[b], kk, kp, kq, snap, extrema) for b in range(g)]
            t = mi.Float(0.0)
            for b in range(g):
                tb = mi.Float(0.0)
                for first, count_, value, _ in parts[b]:
                    jj = dr.minimum(dr.maximum(j, first), first + count_ - 1) - first + 1
                    tb = dr.select((j >= first) & (j < first + count_), value(jj), tb)
                tb = dr.select(is_peak, sl[b].peak, tb)
                if j_ex is not None:
                    tb = dr.select(j == j_ex, sl[b].extra, tb)
                tb = dr.select(j == 0, sl[b].entry, tb)
                t = dr.select(band == b, tb, t)
            # rank = own index in its band (0 for a peak) + the samples of the other groups
            # that come before; ties: lower band first, a band's samples before any peak of
            # the same or a later band
            rank = dr.select(is_peak, 0, mi.UInt32(j))
            for b in range(g):
                e0, ex, pk = sl[b].entry, sl[b].extra, sl[b].peak
                incl = dr.select(is_peak, mi.UInt32(b) <= band, mi.UInt32(b) < band)

                def before(x):
                    return (x < t) | (incl & (x == t))

                cnt = dr.select(before(e0), 1, 0)
                if j_ex is not None:
                    cnt += dr.select(before(ex), 1, 0)
                for _, _, _, counter in parts[b]:
                    cnt += counter(before)
                rank += dr.select(is_peak | (band != b), cnt, 0)
                pk_before = (pk < t) | ((mi.UInt32(b) < band) & (pk == t))
                rank += dr.select(is_peak & (band == b), 0, dr.select(pk_before, 1, 0))
            ts = dr.zeros(mi.Float, na * m)
            dr.scatter(ts, t, r * m + rank)
            # a hit band's extra sample is its box's deepest point; the band's last sample
            # can coincide with it (then AD may take either of the two equal SDF values)
            at_deepest, lam_k = mi.Bool(False), mi.Float(-1.0)
            for b in range(g):
                hb = dr.gather(mi.Bool, slot_hit[b], rows)
                at_deepest = dr.select(band == b, hb & (t == sl[b].deepest), at_deepest)
                # a kink minimum with its weight, taken by a moved sample (or next to a
                # fixed one: the deepest point's sample gets the kink's weight then)
                kinks = sl[b].kinks
                for kt, kl in zip(kinks[0::2], kinks[1::2]):
                    at_kink = (band == b) & (kt >= 0.0) & (kl >= 0.0) & (dr.abs(t - kt) <= KINK_PROBE)
                    lam_k = dr.select(at_kink, kl, lam_k)
            deepest = dr.zeros(mi.UInt32, na * m)
            dr.scatter(deepest, dr.select(at_deepest | (lam_k >= 0.0), band, g), r * m + rank)
            kink_lam = dr.full(mi.Float, -1.0, na * m)
            dr.scatter(kink_lam, lam_k, r * m + rank)
            # gap peaks: the two crossing bands and the envelope weight of the first
            lam, pa, pb = mi.Float(-1.0), mi.Float(0.0), mi.Float(0.0)
            for b in range(g - 1):
                here = is_peak & (band == b)
                lam, pa, pb = [dr.select(here, v, x) for v, x in zip((sl[b].peak_lambda, sl[b].peak_a, sl[b].peak_b), (lam, pa, pb))]
            peak_lam = dr.full(mi.Float, -1.0, na * m)
            dr.scatter(peak_lam, lam, r * m + rank)
            peak_a, peak_b = dr.zeros(mi.UInt32, na * m), dr.zeros(mi.UInt32, na * m)
            dr.scatter(peak_a, mi.UInt32(pa), r * m + rank)
            dr.scatter(peak_b, mi.UInt32(pb), r * m + rank)
            rays = dr.gather(mi.UInt32, ray_idx, sub)
            inst = [dr.gather(mi.UInt32, slot_inst[b], sub) for b in range(g)]
            own = None
            if iso:  # each sample's band
                own = dr.zeros(mi.UInt32, na * m)
                dr.scatter(own, band, r * m + rank)
        # yield outside ``suspend_grad``: the consumer differentiates the integral
        yield SampleGroup(rays, ts, m, active, inst, deepest, (peak_a, peak_b, peak_lam), own, kink_lam, real)
