"""Numerics, one-dimensional searches and lane helpers shared by the integrators.

Dr.Jit 1.5 has no ``softplus`` or ``log1p``; :func:`softplus` and :func:`sigmoid` here are exact
at 0 and overflow-free. The searches run per lane (one bracket per ray or per (slot, ray) pair),
either inside one symbolic loop or unrolled with one kernel per step where the function launches
kernels of its own. The lane helpers build and slice flat arrays without baking their sizes into
kernels (every size that changes from call to call is an opaque value), see
``docs/integrators.md`` ("Kernel shapes").
"""

from __future__ import annotations

import colorsys
from typing import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

#: ``(sqrt 5 - 1) / 2``: the golden-section ratio.
GOLDEN = 0.6180339887498949
#: Hue step between instance colours (the golden angle as a fraction of a turn), their first hue,
#: saturation and value.
COLOUR_HUE_STEP, COLOUR_HUE_START, COLOUR_SATURATION, COLOUR_VALUE = 0.618034, 0.13, 0.75, 0.95


def softplus(x):
    """``log(1 + exp(x))`` without overflow; derivative ``sigmoid(x)`` (0.5 at 0)."""
    return dr.maximum(x, 0.0) + dr.log(1.0 + dr.exp(dr.minimum(x, -x)))


def sigmoid(x):
    """Logistic function with finite values and derivatives for any finite ``x``.

    ``exp(-|x|)`` through a select, not ``dr.abs``: the derivative of ``dr.abs`` at 0 is 0, which
    would leave a latent that starts exactly at 0 (a range's centre) without a gradient.
    """
    z = dr.exp(dr.select(x >= 0, -x, x))
    return dr.select(x >= 0, 1.0 / (1.0 + z), z / (1.0 + z))



def golden_probes(a, b) -> tuple[mi.Float, mi.Float]:
    """The two interior probes of a golden-section bracket ``(a, b)``."""
    return b - GOLDEN * (b - a), a + GOLDEN * (b - a)


def golden_step(state: tuple, f) -> tuple:
    """One golden-section step on ``state = (a, b, x1, x2, f1, f2)`` (bracket, probes, values):
    keeps the side of the lesser value and evaluates ``f`` at one new probe."""
    a, b, x1, x2, f1, f2 = state
    left = f1 < f2
    a2, b2 = dr.select(left, a, x1), dr.select(left, x2, b)
    p1, p2 = golden_probes(a2, b2)
    xn = dr.select(left, p1, p2)
    fn = f(xn)
    return (a2, b2, dr.select(left, xn, x2), dr.select(left, x1, xn),
            dr.select(left, fn, f2), dr.select(left, f1, fn))


def golden_argmin(state: tuple) -> mi.Float:
    """The lesser probe of a golden-section state."""
    return dr.select(state[4] < state[5], state[2], state[3])


def golden_section(fs, brackets, iterations: int, label: str) -> list[mi.Float]:
    """Per lane, ``argmin`` of each unimodal ``fs[i]`` on ``brackets[i] = (a, b)`` by
    ``iterations`` golden-section steps, all functions in one symbolic loop (detached use)."""
    state = [mi.UInt32(0)]
    for f, (a, b) in zip(fs, brackets):
        a, b = mi.Float(a), mi.Float(b)
        x1, x2 = golden_probes(a, b)
        state += [a, b, x1, x2, f(x1), f(x2)]

    def cond(i, *s):
        return i < iterations

    def body(i, *s):
        s = list(s)
        for k, f in enumerate(fs):
            s[6 * k:6 * k + 6] = golden_step(tuple(s[6 * k:6 * k + 6]), f)
        return (i + 1, *s)

    state = dr.while_loop(tuple(state), cond, body, label=label)
    return [golden_argmin(state[1 + 6 * k:7 + 6 * k]) for k in range(len(fs))]


def golden_minimum(f, a: mi.Float, b: mi.Float, iterations: int, traceable: bool, label: str) -> mi.Float:
    """Per lane, ``argmin`` of a unimodal ``f`` on ``(a, b)`` by ``iterations`` golden-section
    steps: one symbolic loop where ``f`` is ``traceable``, else unrolled (one kernel a step;
    ``f`` may launch kernels of its own, as the residual MLP does)."""
    if traceable:
        return golden_section([f], [(a, b)], iterations, label)[0]
    x1, x2 = golden_probes(a, b)
    state = (a, b, x1, x2, f(x1), f(x2))
    for _ in range(iterations):
        state = golden_step(state, f)
        dr.eval(state)  # the same kernel every step
    return golden_argmin(state)


def illinois_root(g, lo: mi.Float, hi: mi.Float, g_lo: mi.Float, g_hi: mi.Float, steps: int,
                  traceable: bool, label: str) -> mi.Float:
    """Per lane, a root of ``g`` in ``[lo, hi]`` (``g_lo < 0 < g_hi``, the values at the ends)
    by ``steps`` steps of regula falsi, Illinois variant (the end kept twice in a row has its
    value halved: superlinear where ``g`` is smooth, never slower than bisection by much):
    the last estimate. One symbolic loop where ``g`` is ``traceable``, else unrolled. Lanes
    whose ends do not bracket a root return a point of ``[lo, hi]``."""
    side = mi.Int32(0)  # -1: lo was replaced last, 1: hi

    def step(t, lo, hi, g_lo, g_hi, side):
        den = g_hi - g_lo
        t = dr.clip(dr.fma(g_lo, (lo - hi) / dr.select(den > 0.0, den, 1.0), lo), lo, hi)
        gt = g(t)
        above = gt > 0.0
        g_lo = dr.select(above & (side == 1), 0.5 * g_lo, g_lo)
        g_hi = dr.select(~above & (side == -1), 0.5 * g_hi, g_hi)
        return (t, dr.select(above, lo, t), dr.select(above, t, hi), dr.select(above, g_lo, gt),
                dr.select(above, gt, g_hi), dr.select(above, mi.Int32(1), mi.Int32(-1)))

    state = (mi.Float(lo), mi.Float(lo), mi.Float(hi), mi.Float(g_lo), mi.Float(g_hi), side)
    if traceable:
        state = dr.while_loop((mi.UInt32(0), *state), lambda i, *s: i < steps,
                              lambda i, *s: (i + 1, *step(*s)), label=label)[1:]
    else:
        for _ in range(steps):
            state = step(*state)
            dr.eval(state)  # the same kernel every step
    return state[0]


def block_successor(n: int, m: int) -> mi.UInt32:
    """Per lane of ``n`` (blocks of ``m`` samples per ray) the index of the next sample in its
    block; the last sample of a block is its own successor."""
    lane = dr.arange(mi.UInt32, n)
    return dr.select((lane % m) == (m - 1), lane, lane + 1)


def block_predecessor(n: int, m: int) -> mi.UInt32:
    """Per lane the index of the previous sample in its block (the first is its own)."""
    lane = dr.arange(mi.UInt32, n)
    return dr.select((lane % m) == 0, lane, lane - 1)


def concat(arrays: Sequence, width: int | None = None, eval_after: Sequence[int] = ()):
    """Concatenate Float (or UInt32) arrays (differentiably) without baking sizes into kernels.

    ``dr.concat`` compiles its offsets into the kernel, so concatenating arrays whose widths change
    every call recompiles every call; here the offsets are opaque. With ``width`` the result has
    that many lanes (zero padding after the arrays). ``eval_after``: indices of arrays after
    whose copy the result is evaluated (the copies up to there in a kernel of their own).
    """
    widths = [dr.width(a) for a in arrays]
    starts = np.concatenate([[0], np.cumsum(widths)[:-1]]).astype(int).tolist()
    total = width if width is not None else int(starts[-1] + widths[-1])
    out = dr.zeros(type(arrays[0]), total)
    evals = set(eval_after)
    for i, (a, w, s0) in enumerate(zip(arrays, widths, starts)):
        dr.scatter(out, a, dr.arange(mi.UInt32, w) + dr.opaque(mi.UInt32, int(s0)))
        if i in evals:
            dr.eval(out)
    return out




def pick(values: list[mi.Float], i: mi.UInt32) -> mi.Float:
    """``values[i - 1]`` per lane (``i`` in ``1..len(values)``)."""
    out = values[0]
    for idx, v in enumerate(values[1:], start=2):
        out = dr.select(i == idx, v, out)
    return out


def sorted_arrays(values: list[mi.Float]) -> list[mi.Float]:
    """Per lane the values sorted ascending (odd-even transposition network: ``n`` rounds of
    compare-exchanges, for a handful of arrays)."""
    out = list(values)
    for r in range(len(out)):
        for i in range(r % 2, len(out) - 1, 2):
            out[i], out[i + 1] = dr.minimum(out[i], out[i + 1]), dr.maximum(out[i], out[i + 1])
    return out


def concat_groups(pieces: list[list]):
    """:func:`concat` of every group's pieces (``pieces[group][piece]``), each
    group's in a kernel of its own. Dr.Jit evaluates pending scatters of equal width together,
    so a concatenation in one go put two groups whose widths happened to match in one kernel
    (and one whose width matched no other's in a kernel of its own): kernels compiled anew at
    random steps, whenever the groups' sizes coincided differently."""
    ends = np.cumsum([len(grp) for grp in pieces]) - 1
    return concat([a for grp in pieces for a in grp], eval_after=ends.tolist())


def block_of(values: mi.Float, b: int, n: int) -> mi.Float:
    """Block ``b`` of ``n`` lanes of a block-major array (a slot of the (slot, ray) pairs, a
    candidate of the kink search); the offset is opaque, as ``n``
    changes every call."""
    return dr.gather(type(values), values, dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, b * n))


def compress_wide(mask: mi.Bool) -> tuple[mi.UInt32, mi.Bool]:
    """``dr.compress(mask)`` and two padding lanes after it (index clamped into ``mask``), and
    which lanes are real. Arrays of width 1 read as scalars, whose values Dr.Jit bakes into
    kernels as literals (each new value compiled them anew), and a pass that runs only where
    some lane needs it, or a padding done only for few lanes, compiles its kernels at the first
    such call, deep into an optimisation: this runs the same kernels for any count."""
    n = dr.width(mask)
    no = dr.opaque(mi.UInt32, n)
    ext = dr.zeros(mi.Bool, n + 2)
    dr.scatter(ext, mask, dr.arange(mi.UInt32, n))
    dr.scatter(ext, True, dr.arange(mi.UInt32, 2) + no)
    idx = dr.compress(ext)
    return dr.minimum(idx, no - 1), idx < no


def count_prefix(n: int, value, before) -> mi.UInt32:
    """How many of the per-lane sorted samples ``value(i)``, ``i = 1..n``, satisfy ``before``
    (it holds for a prefix of them): a binary search on the samples themselves."""
    return dr.binary_search(1, n + 1, lambda i: (i <= n) & before(value(dr.minimum(i, n)))) - 1



def instance_colours(n: int) -> list[tuple[float, float, float]]:
    """A fixed, distinguishable RGB colour per instance (golden-angle hues)."""
    return [colorsys.hsv_to_rgb((COLOUR_HUE_START + COLOUR_HUE_STEP * k) % 1.0, COLOUR_SATURATION, COLOUR_VALUE)
            for k in range(n)]
