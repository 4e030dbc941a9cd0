"""The adaptive sampler's per-ray band slots: their anchors, and where a band's samples sit.

A ray meets a few enlarged boxes; each gets a slot (sorted by the box's deepest point along the
ray) whose detached anchors (:class:`Slot`) say where the band's samples go: the enlarged box's
entry, the band's two halves around its centre (the surface entry, or the closest approach of a
miss), the deepest point, the tails over the rest of the chord (with the residual field) and the
gap peak before the next slot. :func:`sub_sample` is the one formula for the samples between two
anchors, for their values and their ranks alike.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from ..common import count_prefix
from .settings import SamplingContext

#: The band anchors (:class:`Slot` fields) that an isolated ray's band keeps with the residual
#: field: the centre (surface entry, or a miss's least ``B + R``), the band's end, the extra
#: sample (a hit's least ``B + R``) and the enlarged box's exit.
ISOLATED_ANCHORS = ("mid", "hi", "extra", "tail_end")
#: Minima of ``B + R`` at kinks and bends of ``B`` per (slot, ray) pair that take a moved
#: sample: on the integrator benchmark's 6-box scene 24 of 35.5k pairs had three, one of 16k
#: pairs on 40 random scenes five.
KINK_MINIMA = 2


@dataclass(frozen=True)
class Picked:
    """Per ray, the box of one band slot as :func:`~.bands.adaptive_bands`
    picks it (detached arrays over the rays). A dataclass, not a named tuple: ``dr.eval``
    looks inside dataclasses, not inside named tuples."""

    valid: mi.Bool  #: the ray has this slot (it meets that many enlarged boxes)
    entry: mi.Float  #: enlarged box entry along the ray
    exit: mi.Float  #: enlarged box exit
    tstar: mi.Float  #: the box SDF's least point along the ray (closest approach / deepest point)
    centre: mi.Float  #: surface entry (a hit) or closest approach (a miss)
    surface_exit: mi.Float  #: where the ray leaves the box itself
    hit: mi.Bool  #: the ray enters the box


class GapPeak(NamedTuple):
    """Per ray, the scene SDF's maximum after a slot (:func:`~.bands.gap_peaks`)."""

    t: mi.Float  #: where along the ray
    ok: mi.Bool  #: the gap exists
    lam: mi.Float  #: envelope weight of slot ``a``, ``-1`` where the peak is no crossing
    a: mi.Float  #: the slot rising into the peak (an exact small integer)
    b: mi.Float  #: the slot falling from it
    f: mi.Float  #: the scene's box SDF there (the lesser of the two slots')


@dataclass(frozen=True)
class Slot:
    """Per ray, one band's detached sample anchors (:func:`~.bands.adaptive_bands`;
    arrays over the rays, an invalid slot at ``far``). A dataclass, so ``dr.eval`` evaluates
    every array of it (it does not look inside named tuples)."""

    entry: mi.Float  #: enlarged box entry: the band's first sample
    lo: mi.Float  #: start of the band's first half
    mid: mi.Float  #: the band's centre: surface entry, closest approach or least ``B + R``
    hi: mi.Float  #: end of the band's second half
    extra: mi.Float  #: the extra sample: a hit's deepest point, else the far end / a tail split
    peak: mi.Float  #: the gap peak after the band (``extra`` where there is none)
    peak_lambda: mi.Float  #: the peak's envelope weight (``-1``: no crossing), see :class:`GapPeak`
    peak_a: mi.Float  #: the peak's rising slot
    peak_b: mi.Float  #: the peak's falling slot
    tail_end: mi.Float  #: end of the second tail (the enlarged box's exit)
    deepest: mi.Float  #: the sample at the box's least ``B + R`` (a hit's deepest point)
    #: the minima of ``B + R`` at kinks of ``B`` that the moved samples take, and their envelope
    #: weights (``t0, lambda0, t1, ...``; ``t = -1``: none, ``lambda = -1``: beside a bend), see
    #: :func:`~.residual_search.kink_minima`
    kinks: tuple = ()
    #: band and tail positions moved to the extrema of ``B + R``, in the order
    #: :func:`~.extrema.snapped_slots` returns them (empty: not moved)
    moved: tuple = ()
    #: with the residual field, an isolated ray's samples of the band after its entry, sorted:
    #: the anchors :data:`ISOLATED_ANCHORS`, the extrema of ``B + R`` along the chord and its
    #: minima at kinks of ``B`` (:func:`~.extrema.extremum_samples`)
    isolated: tuple = ()

    def map(self, f) -> "Slot":
        """The slot with ``f`` applied to every array (the tuples' included)."""
        tuples = ("moved", "kinks", "isolated")
        return Slot(**{fd.name: f(getattr(self, fd.name)) for fd in fields(self) if fd.name not in tuples},
                    **{name: tuple(f(v) for v in getattr(self, name)) for name in tuples})

    def arrays(self) -> tuple:
        """Every array of the slot, the kinks', the moved and the isolated layout's positions last."""
        return (*(getattr(self, fd.name) for fd in fields(self) if fd.name not in ("moved", "kinks", "isolated")),
                *self.kinks, *self.moved, *self.isolated)


@dataclass
class Bands:
    """The band search's result (:func:`~.bands.adaptive_bands`): the rays that meet an enlarged
    box and, per slot, their bands (arrays over those rays)."""

    rays: mi.UInt32  #: indices of the rays meeting at least one enlarged box
    count: mi.UInt32 | None  #: per ray its number of bands (``None``: no ray meets a box)
    slots: list  #: per slot a :class:`Slot`; a ray's valid slots come first
    inst: list  #: per slot the band's instance (``num_instances`` for an empty slot)
    hit: list  #: per slot whether the ray enters the box itself
    isolated: mi.Bool | None  #: per ray whether it gets the isolated layout
    grid: object = None  #: the chord grid of the residual search (:class:`~.residual_search.ChordGrid`)


class SampleGroup(NamedTuple):
    """The adaptive samples of the rays with one band count and layout
    (:func:`~.layout.adaptive_groups`)."""

    rays: mi.UInt32  #: the group's rays (indices into the batch)
    t: mi.Float  #: ``m`` sorted sample positions per ray, ray-major
    m: int  #: samples per ray
    active: mi.Bool  #: masks the group's two padding rays (see :func:`compress_wide`)
    inst: list  #: per band slot the instance of each ray's band (``mi.UInt32``)
    deepest: mi.UInt32  #: per sample the band whose deepest point it is (``len(inst)``: none)
    #: per sample the two bands crossing at a gap peak and the first's envelope weight
    #: (``-1``: no peak), see :func:`~.bands.gap_peaks`
    peak: tuple
    own: mi.UInt32 | None  #: per sample its band in an isolated group (``None`` otherwise)
    #: per sample at a kink of its band's box where ``B + R`` has a minimum (``deepest`` names
    #: the band) the envelope weight of the face before it, else ``-1`` (see :class:`Slot`)
    kink_lam: mi.Float
    real: int  #: the group's rays without the padding



def sub_sample(a, b, i, k: int, dense_at_b: bool = False):
    """``i``-th (1..k) sample of the sub-band ``(a, b]``; the one formula for values and ranks.

    The fraction ``u = i / k`` is warped to ``u^1.25`` (``1 - (1 - u)^1.25`` with
    ``dense_at_b``), so samples crowd mildly towards the band's centre (the surface or the
    closest approach), where opacity accrues and labels switch. Labels vs the reference,
    3-12 boxes, s = 1-10, K = 16: p99 0.0008-0.0046 instead of 0.0009-0.0057, max
    0.0022-0.0114 instead of 0.0045-0.0140 (exponent 1.5: p99 down to 0.0033, max up to
    0.0178; 2: max up to 0.0189).
    """
    u = mi.Float(i) * (1.0 / k)
    v = 1.0 - u if dense_at_b else u
    v = v * dr.sqrt(dr.sqrt(v))  # v^1.25
    return dr.fma(b - a, 1.0 - v if dense_at_b else v, a)  # one rounding wherever it is evaluated

def count_before(a, b, k: int, before, dense_at_b: bool = False, n: int | None = None):
    """Number of samples ``i = 1..n`` (default ``k``) of the ``k`` of sub-band ``(a, b]`` for
    which ``before`` holds (it holds for a prefix of them: the samples are sorted). A binary
    search on the samples themselves: inverting the sample formula misplaced ranks by more
    than one where a band is narrow next to its distance (float rounding), which left rays
    unsorted."""
    return count_prefix(k if n is None else n, lambda i: sub_sample(a, b, i, k, dense_at_b), before)


def band_layout(ctx: SamplingContext, extrema: bool, kk: int = 0) -> tuple[int | None, int]:
    """Per band of :func:`~.layout.adaptive_groups`: the index of its extra sample and its samples,
    the gap peak included. The full layout: entry, ``kk`` band samples, the first tail, the
    extra sample, the second tail, the peak (:meth:`~.settings.SamplingContext.tail_samples`). An isolated band with
    the residual field (``extrema``): entry, :attr:`Slot.isolated` (the extra sample among
    them: index ``None``), the peak."""
    if extrema:
        return None, 1 + len(ISOLATED_ANCHORS) + ctx.settings.isolated_extrema + KINK_MINIMA + 1
    kp, kq = ctx.tail_samples()
    j_ex = kk + kp + 1
    return j_ex, j_ex + kq + 2
