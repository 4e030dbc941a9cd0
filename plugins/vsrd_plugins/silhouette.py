r"""Instance-aware NeuS silhouette integrator (``vsrd_silhouette``).

.. pluginparameters::

 * - num_instances, centres, sizes, yaws, velocities, dynamic
   - |int|, |string|
   - The boxes (see :func:`vsrd_plugins.sdf.instance_properties`). Ray time is the frame offset
     used to move dynamic boxes: ``centre(t) = centre + dynamic * velocity * t``.
 * - residual
   - |bool|
   - Add the hypernetwork residual distance field to every box SDF. (Default: false)
 * - residual_seed, residual_shift, residual_gradients
   - |int|, |float|, |string|
   - The residual field's initialisation seed and output shift, and how its gradients are
     computed: ``fused`` (hand-written derivatives around one cooperative-vector kernel, LLVM) or
     ``tensor`` (Dr.Jit AD through tensor-mode matmuls, the reference). (Default: 0, 3, fused)
 * - sampling
   - |string|
   - ``adaptive`` (default) or ``dense`` (paper-faithful reference, see below).
 * - sharpness, temperature
   - |float|
   - NeuS sharpness ``s`` (1/m) and softmin temperature ``tau`` (m). Exposed by ``traverse()`` as
     opaque non-differentiable values: changing them each step does not recompile.
     (Default: 10, 0.1)
 * - band_samples, max_bands, reach
   - |int|, |int|, |float|
   - Adaptive sampling: ``K`` samples per band, at most ``B`` bands (instances) per ray (0: no
     limit), band half-width ``reach / s`` and culling margin ``reach * max(1/s, tau)``.
     (Default: 16, 0, 8)
 * - residual_scan, residual_golden, residual_tail, residual_tail_scan
   - |int|
   - Adaptive sampling with the residual: points scanned per band for the least ``B + R``
     along the ray, golden-section steps refining it (0 scan points: use the box's least
     ``B``), tail samples per band covering the rest of the box's chord, where ``B + R``
     can dip again (0: none), and detached scan points per band and tail sample that move
     the samples to the local extrema of ``B + R`` they find (0: none). (Default: 4, 0, 12, 3)
 * - residual_grid, residual_lattice
   - |float|
   - Adaptive sampling with the residual: the scans above and the detached values that sort
     samples into frozen and not (see ``residual_sparse_gradients``) read ``R`` interpolated
     from exact values on a grid along each band's chord, spaced ``residual_grid`` radians of the
     encoding's highest frequency apart (0: evaluate ``R`` at every scan point and sample).
     Where a ray batch is dense enough that tabulating ``R`` per instance costs less, those
     grid values come from a box-local lattice spaced ``residual_lattice`` radians apart
     (tricubic; 0: never). (Default: 0.35, 0.35)
 * - residual_sparse_gradients
   - |bool|
   - Adaptive sampling with the residual: samples strictly inside a monotone run of the scene
     SDF with one instance near keep their values but leave the AD graph (their derivative
     vanishes; see below). (Default: true)
 * - isolated_rays, isolated_band_samples, isolated_extrema
   - |bool|, |int|, |int|
   - Adaptive sampling: rays whose enlarged boxes are disjoint along them get
     ``isolated_band_samples`` band samples per box instead of ``K`` (without the residual
     field), or their bands' anchors and the extrema of ``B + R`` along them (with it, where a
     band has at most ``isolated_extrema`` extrema and the batch has enough such rays to pay
     for their sample groups), and evaluate only that box at them (see below). (Default: true,
     1, 3)
 * - coarse_samples, fine_samples
   - |int|
   - Dense sampling: stratified coarse and importance fine sample counts. (Default: 100, 100)
 * - ridge_gradients
   - |bool|
   - Give each ray's deepest sample inside a box the envelope gradient of the box's minimum
     along the ray instead of AD's one-sided gradient of the max over faces (see below; values
     are unchanged). (Default: true)
 * - near, far
   - |float|
   - Integration range along each ray. (Default: 0, 100)

Every box parameter (``vsrd.box_dims``, ``vsrd.box_centre``, ``vsrd.box_yaw``,
``vsrd.box_velocity``), the residual field's embedding and hypernetwork weights
(``vsrd.rdf_*``) and the schedule values (``vsrd.sharpness``, ``vsrd.temperature``) appear in
``mi.traverse(scene)`` when the integrator has ``id="vsrd"``.

The integral (paper eq. 6-8)
----------------------------

For a ray with samples ``t_0 < ... < t_{M-1}`` and scene SDF values ``f_i = min_k F_k(o + t_i d)``
the discrete NeuS opacity of interval ``i`` (NeuS eq. 13) is

.. math::

   \alpha_i = \max\Big(\frac{\Phi_s(f_i) - \Phi_s(f_{i+1})}{\Phi_s(f_i)}, 0\Big),
   \qquad \Phi_s(x) = \mathrm{sigmoid}(s x),

evaluated in log space, stable for any ``s``:
``log(1 - alpha_i) = min(softplus(-s f_i) - softplus(-s f_{i+1}), 0)``. Transmittance
``T_i = exp(sum_{j<i} log(1 - alpha_j))``, weight ``w_i = T_i alpha_i``, and the rendered soft
label of instance ``k`` is

.. math::

   \hat S_k = \sum_i \frac{w_i}{2} \sum_{j=1,2} \mathrm{softmin}_k\big(F_{i,j}^* / \tau\big),
   \qquad F_{k,i,j}^* = F_k(x_i) + \theta_{i,j} \big(F_k(x_{i+1}) - F_k(x_i)\big),

where ``theta_{i,j}`` are the positions at which the interval has accrued the fractions
``1/2 -+ 1/(2 sqrt 3)`` of its opacity with ``f`` linear over it (two-point Gauss-Legendre in
the accrued opacity, :meth:`~VSRDSilhouetteIntegrator._accrual_quantiles`; both the surface
crossing in the sharp limit). The background label is ``1 - sum_k S_k``. Because the opacities telescope
over monotone stretches of ``f``, the result depends on where the samples resolve the minima,
maxima and descents of ``f``, which is what the two sampling strategies target:

* ``dense``: ``coarse_samples`` stratified samples over ``[near, far]`` (no gradients), then
  ``fine_samples`` importance samples from the coarse weights (guarded against rays whose coarse
  weights vanish), merged in order; every instance evaluated at every sample.
* ``adaptive``: per ray and instance, a ray/box slab test against the box enlarged by
  ``reach * max(1/s, tau)`` culls the instance: beyond that margin its opacity and its softmin
  share next to a surface are below ``exp(-reach)`` (the residual is non-negative, so ``B + R``
  is beyond it too, and the residual is evaluated only inside that margin), so it is not
  evaluated at that ray's samples at all (one SDF evaluation per sample and *met* instance, not
  per instance of the scene); for each remaining instance a
  detached golden-section search on the (convex) box SDF finds the closest approach ``t*`` and
  the slab test the surface entry. Each such instance gets a band of ``K`` samples of half-width
  ``reach / s`` at its entry (hit) or ending at ``t*`` (miss), plus its enlarged-box entry and
  the closest approach, so the minimum of ``f`` is sampled exactly (for a miss the gradient is
  then the exact envelope gradient). Between consecutive deepest points a second detached
  golden-section search finds where the scene SDF stops rising and starts falling into the next
  box (its maximum there: it is unimodal between two consecutive minima of convex functions), one
  more sample per band: the next descent's opacity telescopes from there, and without it a ray
  grazing two neighbours lost part of it (labels off by up to 0.03 at s = 10). At most ``B``
  bands (nearest deepest point first) per ray, and only those
  ``B`` instances are evaluated on it. With the residual field the instance SDF ``B + R`` has
  its minimum off the box's (``R`` decides along a ray grazing a face): a detached scan of
  ``B + R`` per band (one batched residual evaluation; golden-section steps can refine it) moves
  the band's minimum sample there, and ``residual_tail`` more samples per band cover the rest of
  the chord (half between a reach past a hit's entry and the minimum, half from the band's end
  to the enlarged box's exit; where the band already ends at its minimum, both halves share the
  rest of the chord; a miss whose minimum lies far into its chord puts it at its extra sample
  and spreads the band before it, :meth:`~VSRDSilhouetteIntegrator._lengthwise_miss`), where
  ``B + R`` can dip again. The opacity telescopes over each
  monotone run of ``f``, so with the field every local extremum of ``B + R`` that a detached
  scan (``residual_tail_scan`` points per sample) finds, and every minimum of ``B + R`` at a
  kink of ``B`` inside a box or beside a sharp bend of it where a ray passes an edge
  (:meth:`~VSRDSilhouetteIntegrator._kink_minima`), claims a band or tail sample in order
  along the ray (:meth:`~VSRDSilhouetteIntegrator._snapped_positions`); the gap peaks move to
  where the two instance SDFs cross (:meth:`~VSRDSilhouetteIntegrator._residual_peaks`);
  those scans and searches read ``R``
  interpolated from a grid of exact values along the chord (``R`` is smooth, ``B`` exact,
  :meth:`~VSRDSilhouetteIntegrator._chord_grid`; filled from a per-instance lattice of ``R``
  where the ray batch is dense, :meth:`~VSRDSilhouetteIntegrator._residual_lattice`), and run
  over the (slot, ray) pairs that hold a box only (:class:`PairScan`). Rays that meet no enlarged box
  return background at zero cost (they are compacted away). A ray whose enlarged-box intervals
  are disjoint (isolated, :meth:`~VSRDSilhouetteIntegrator._isolated`) has at each band sample
  every other box beyond its culling margin, so its labels are the band's opacity, which
  telescopes exactly between the entry, centre and deepest-point samples: it gets
  ``isolated_band_samples`` band samples and only the band's own box is evaluated at them (the
  others stand in as :data:`ISOLATED_ELSEWHERE`). With the residual field the opacity telescopes
  over each monotone run of ``B + R``, so an isolated band needs its entry, centre, end, least
  ``B + R``, exit and the extrema of ``B + R`` along the chord, which a detached hysteresis scan
  finds (:meth:`~VSRDSilhouetteIntegrator._chord_extrema`), and the minima at kinks of ``B``: 11
  samples instead of the full layout's 31, where a band has at most ``isolated_extrema`` extrema
  (6 boxes / 16k rays: 90 % of the rays; those rays also skip the full layout's scans for moved
  samples), in batches where the isolated rays save more samples than their groups cost
  (:meth:`~VSRDSilhouetteIntegrator._worth_isolating`). Only sample positions are detached; SDF values
  at samples carry gradients, except, with the residual field (``residual_sparse_gradients``),
  at samples strictly inside a monotone run of ``f`` with one instance near: the telescoping
  gives them zero derivative, so they keep their values but leave the AD graph and the MLP's
  backward pass (:meth:`~VSRDSilhouetteIntegrator._frozen_lanes`).

Gradients at a box's interior ridges
------------------------------------

Where a ray passes through a box, the telescoping makes its opacity ``1 - Phi_s(f_min) /
Phi_s(f_0)``: the label's gradient is the gradient of the SDF at the ray's deepest sample. Inside
a box that sample lies on a ridge of ``max`` over the face planes, where AD follows one face
(whichever side of the ridge the sample fell on), while the derivative of the true minimum blends
the two faces meeting there (Danskin; :func:`~vsrd_plugins.sdf.box_sdf_ray_local`). One-sided,
the gradients of two samplings disagree ray by ray, and neither is the derivative of the
integral. With ``ridge_gradients`` (default) the deepest sample of each ray in each box (the
adaptive sampler's exact closest approach of an entered box; for ``dense`` and
:meth:`integrate_at` the sample of least SDF, within a face tolerance of twice the local
spacing) carries the envelope gradient; only those samples pay for it. The same holds at the
adaptive sampler's gap peaks, where two boxes' distances cross at a maximum of the scene SDF:
there its gradient is the blend of the two that keeps its slope along the ray zero; and at the
samples on kinks of ``B`` where ``B + R`` has a minimum, with the weight that makes ``B + R``'s
own slope zero (:func:`~vsrd_plugins.sdf.ridge_faces`).

Usage
-----

.. code-block:: python

    import vsrd_mi, mitsuba as mi
    from vsrd_plugins.sdf import instance_properties
    scene = mi.load_dict({'type': 'scene', 'sensor': {...},
        'integrator': {'type': 'vsrd_silhouette', 'id': 'vsrd',
                       **instance_properties(centres, sizes, yaws)}})
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=0.01, params={k: params[k] for k in ('vsrd.box_centre',)})
    labels = scene.integrator().render_rays(origins, directions, times)  # N + 1 Float arrays
"""

from __future__ import annotations

import math

from dataclasses import dataclass, fields, replace
from typing import Callable, Iterator, NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np

from .sdf import (LATTICE_LOOKUP_COST, RIDGE_TOLERANCE, InstanceField, ResidualLattice, box_normal_local, box_ray_bends, box_ray_kinks, box_sdf_local, concat, envelope_blend,
                  envelope_weight, ray_box_interval, scene_sdf, softmin_labels, softplus)

GOLDEN = 0.6180339887498949
#: Below this interval opacity the labels are taken at uniform quantiles (see _accrual_quantiles).
ACCRUAL_MIN_OPACITY = 1e-6
#: Below this |s * (f_b - f_a)| an interval's SDF is treated as flat (uniform quantiles).
ACCRUAL_MIN_SLOPE = 1e-4
#: Intervals starting deeper than ``-s * f_a`` > this use uniform quantiles (exp overflow guard; only
#: rays starting inside a box reach such depths with non-zero transmittance).
ACCRUAL_MAX_DEPTH = 30.0
#: Opacity fractions of an interval at which its labels are evaluated (two-point Gauss-Legendre).
GAUSS_QUANTILES = (0.5 - 0.5 / 3.0 ** 0.5, 0.5 + 0.5 / 3.0 ** 0.5)
#: Stand-in SDF value of an isolated ray's other bands' instances at a band's samples (beyond
#: any culling margin: out of the scene SDF's minimum and the softmin).
ISOLATED_ELSEWHERE = 1e6
#: Gap peaks: boxes on each side of a gap (by deepest point) whose least SDF is searched
#: (see VSRDSilhouetteIntegrator._gap_peaks).
GAP_WINDOW = 4
#: Sparse gradients: a sample is frozen only where its scene SDF differs from both neighbours'
#: by more than this (m). The detached values (fused MLP) and the graph's (tensor-mode MLP)
#: differ in rounding, and samples moved to an extremum often sit within 1e-7 of a neighbour:
#: without the margin, such a pair could be ordered one way in the detached values and the
#: other in the graph, which froze a sample the graph saw as the minimum (box gradient off by
#: 0.25 % relative on a 3-box test scene instead of < 0.05 %).
MONOTONE_TOLERANCE = 1e-5
#: Moved samples (:meth:`VSRDSilhouetteIntegrator._snapped_positions`): a local extremum of
#: the scan of ``B + R`` claims a sample only where it differs from a neighbouring scan point
#: by more than this (m; above the chord grid's interpolation wiggles on flat stretches).
SNAP_PROMINENCE = 2e-4
#: Probe distance (m) on either side of a kink of ``B`` (:meth:`VSRDSilhouetteIntegrator._kink_minima`).
KINK_PROBE = 1e-3
#: Golden-section steps that place a moved sample's extremum between the scan points around it
#: (:meth:`VSRDSilhouetteIntegrator._snapped_positions`): the bracket of two scan intervals
#: shrinks 47x, to a few millimetres. The parabola through the three scan points missed the
#: extrema of trained residual fields (steeper than at their initialisation) by up to 0.14 m.
SNAP_GOLDEN = 8
#: Golden-section steps that find the minimum of ``B + R`` beside a bend of ``B`` (or beside a
#: kink, off it) between two of its probes (:meth:`VSRDSilhouetteIntegrator._kink_minima`):
#: the bracket shrinks 320x, to well under a millimetre for the widest bends.
KINK_GOLDEN = 12
#: Regula falsi steps (Illinois) that move a gap peak to the crossing of two instance SDFs
#: ``B + R`` (:meth:`VSRDSilhouetteIntegrator._residual_peaks`); they converge superlinearly
#: where ``F_a - F_a'`` is smooth, and bisection's 20 steps (10 m to 10 um) cost 19 ms a step
#: on the integrator benchmark (6 boxes, 16k rays).
PEAK_STEPS = 8
#: Minima of ``B + R`` at kinks and bends of ``B`` per (slot, ray) pair that take a moved
#: sample (:meth:`VSRDSilhouetteIntegrator._kink_minima`): on the integrator benchmark's 6-box
#: scene 24 of 35.5k pairs had three, one of 16k pairs on 40 random scenes five.
KINK_MINIMA = 2
#: The fixed cost of a sample group of :meth:`VSRDSilhouetteIntegrator._adaptive_groups` with
#: the residual field (its kernel launches and Python tracing, ~2.5 ms here), in samples (~0.1 us
#: each): isolated rays with the residual field get a group only where they save more.
GROUP_COST_SAMPLES = 25000
#: The band anchors (:class:`Slot` fields) that an isolated ray's band keeps with the residual
#: field (:meth:`VSRDSilhouetteIntegrator._extremum_samples`): the centre (surface entry, or a
#: miss's least ``B + R``), the band's end, the extra sample (a hit's least ``B + R``) and the
#: enlarged box's exit.
ISOLATED_ANCHORS = ("mid", "hi", "extra", "tail_end")
#: Scan points per chord-grid cell of :meth:`VSRDSilhouetteIntegrator._chord_extrema`.
EXTREMUM_SCAN = 2
#: Fewest grid points per chord of :meth:`VSRDSilhouetteIntegrator._chord_grid`.
GRID_MIN_POINTS = 4
#: Monotone margin (m) with which interpolated values sort samples into frozen or not
#: (:meth:`VSRDSilhouetteIntegrator._grid_values`): above the interpolation error (p9999 9e-4 m).
GRID_TOLERANCE = 1e-3
#: Above the float32 difference (m) between a lane's box SDF from its box-local ray
#: (:class:`ChordGrid`) and from its world-frame point (:meth:`~vsrd_plugins.sdf.InstanceField.lane_sdfs`).
REACH_ROUNDING = 1e-4


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


class _EvalTogether(dr.CustomOp):
    """Identity on a list of arrays that evaluates them, and in the reverse pass their
    adjoints, in one kernel. Without it each consumer of the adjoints (e.g. the scatter-add
    reversing a gather of every instance's SDF) evaluates its own copy of the shared
    expression (the softmin's Jacobian over all instances): 12 kernels of ~930 operations in
    the dense sampler's backward pass instead of one."""

    def eval(self, xs):
        xs = [mi.Float(x) for x in xs]
        dr.eval(xs)
        return xs

    def forward(self):
        self.set_grad_out(self.grad_in("xs"))

    def backward(self):
        g = list(self.grad_out())
        dr.eval(g)
        self.set_grad_in("xs", g)

    def name(self):
        return "EvalTogether"


class _NextSample(dr.CustomOp):
    """Each lane's successor within its ray's block of ``m`` samples (the last sample of a
    block is its own successor), for a list of arrays. The reverse pass gathers from the
    predecessor instead of scatter-adding into it: no atomics (as a plain gather's reverse,
    they were the largest integral kernel of the adaptive sampler's backward pass)."""

    def eval(self, xs, m: int):
        self.m = m
        self.n = dr.width(xs[0])
        nxt = block_successor(self.n, m)
        return [dr.gather(mi.Float, x, nxt) for x in xs]

    def forward(self):
        nxt = block_successor(self.n, self.m)
        self.set_grad_out([dr.gather(mi.Float, g, nxt) for g in self.grad_in("xs")])

    def backward(self):
        lane = dr.arange(mi.UInt32, self.n)
        first, last = (lane % self.m) == 0, (lane % self.m) == (self.m - 1)
        prev = block_predecessor(self.n, self.m)
        grads = list(self.grad_out())
        dr.eval(grads)  # together: a gather would evaluate each alone
        out = [dr.select(first, 0.0, dr.gather(mi.Float, g, prev)) + dr.select(last, g, 0.0)
               for g in grads]
        dr.eval(out)
        self.set_grad_in("xs", out)

    def name(self):
        return "NextSample"


@dataclass(frozen=True)
class Picked:
    """Per ray, the box of one band slot as :meth:`VSRDSilhouetteIntegrator._adaptive_bands`
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
    """Per ray, the scene SDF's maximum after a slot (:meth:`VSRDSilhouetteIntegrator._gap_peaks`)."""

    t: mi.Float  #: where along the ray
    ok: mi.Bool  #: the gap exists
    lam: mi.Float  #: envelope weight of slot ``a``, ``-1`` where the peak is no crossing
    a: mi.Float  #: the slot rising into the peak (an exact small integer)
    b: mi.Float  #: the slot falling from it
    f: mi.Float  #: the scene's box SDF there (the lesser of the two slots')


@dataclass(frozen=True)
class Slot:
    """Per ray, one band's detached sample anchors (:meth:`VSRDSilhouetteIntegrator._adaptive_bands`;
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
    #: :meth:`VSRDSilhouetteIntegrator._kink_minima`
    kinks: tuple = ()
    #: band and tail positions moved to the extrema of ``B + R``, in the order
    #: :meth:`VSRDSilhouetteIntegrator._snapped_slots` returns them (empty: not moved)
    moved: tuple = ()
    #: with the residual field, an isolated ray's samples of the band after its entry, sorted:
    #: the anchors :data:`ISOLATED_ANCHORS`, the extrema of ``B + R`` along the chord and its
    #: minima at kinks of ``B`` (:meth:`VSRDSilhouetteIntegrator._extremum_samples`)
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


@dataclass(frozen=True)
class ChordGrid:
    """Exact residuals ``R`` on a grid over each (slot, ray) pair's enlarged-box chord, and
    ``F = B + R`` from them with ``B`` exact and ``R`` interpolated (Catmull-Rom: C1, exact for
    quadratics), built by :meth:`VSRDSilhouetteIntegrator._chord_grid` (detached arrays; pairs
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
    :meth:`VSRDSilhouetteIntegrator._residual_minima` and
    :meth:`VSRDSilhouetteIntegrator._snapped_positions` (pairs slot-major, as
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


class SampleGroup(NamedTuple):
    """The adaptive samples of the rays with one band count and layout
    (:meth:`VSRDSilhouetteIntegrator._adaptive_groups`)."""

    rays: mi.UInt32  #: the group's rays (indices into the batch)
    t: mi.Float  #: ``m`` sorted sample positions per ray, ray-major
    m: int  #: samples per ray
    active: mi.Bool  #: masks the group's two padding rays (see :func:`compress_wide`)
    inst: list  #: per band slot the instance of each ray's band (``mi.UInt32``)
    deepest: mi.UInt32  #: per sample the band whose deepest point it is (``len(inst)``: none)
    #: per sample the two bands crossing at a gap peak and the first's envelope weight
    #: (``-1``: no peak), see :meth:`VSRDSilhouetteIntegrator._gap_peaks`
    peak: tuple
    own: mi.UInt32 | None  #: per sample its band in an isolated group (``None`` otherwise)
    rows: mi.UInt32  #: the group's rays as indices into the band search's rays (its pairs' rays)
    #: per sample at a kink of its band's box where ``B + R`` has a minimum (``deepest`` names
    #: the band) the envelope weight of the face before it, else ``-1`` (see :class:`Slot`)
    kink_lam: mi.Float
    real: int  #: the group's rays without the padding


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
    """:func:`~vsrd_plugins.sdf.concat` of every group's pieces (``pieces[group][piece]``), each
    group's in a kernel of its own. Dr.Jit evaluates pending scatters of equal width together,
    so a concatenation in one go put two groups whose widths happened to match in one kernel
    (and one whose width matched no other's in a kernel of its own): kernels compiled anew at
    random steps, whenever the groups' sizes coincided differently."""
    ends = np.cumsum([len(grp) for grp in pieces]) - 1
    return concat([a for grp in pieces for a in grp], eval_after=ends.tolist())


def block_of(values: mi.Float, b: int, n: int) -> mi.Float:
    """Block ``b`` of ``n`` lanes of a block-major array (a slot of the (slot, ray) pairs, a
    candidate of :meth:`VSRDSilhouetteIntegrator._kink_minima`); the offset is opaque, as ``n``
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


@dataclass(frozen=True)
class SamplingConfig:
    """Ray sampling settings of :class:`VSRDSilhouetteIntegrator` (see the plugin table)."""

    sampling: str = "adaptive"
    band_samples: int = 16
    max_bands: int = 0  # 0: every instance a ray meets gets a band
    reach: float = 8.0
    golden_iterations: int = 24
    #: With the residual field: points scanned per band for the minimum of the instance SDF
    #: ``B + R`` along the ray (0: use the box's minimum), and golden-section steps refining the
    #: best (see :meth:`VSRDSilhouetteIntegrator._residual_minima`).
    residual_scan: int = 4
    #: 0 by default: with the tail samples and two-point labels, 8 refinement steps changed the
    #: benchmark's labels by nothing measurable (max 0.0060 vs 0.0058 without; 32 random 2-3-box
    #: scenes: mean p99 0.0048 vs 0.0052) and cost a quarter of a 1000-ray residual step.
    residual_golden: int = 0
    #: With the residual field: samples per hit band from its least ``B + R`` to the enlarged
    #: box's exit, where ``B + R`` can have further local minima (a ray along a face: the
    #: residual's wiggles against a nearly constant ``B``); see :meth:`_tail_samples`. 8 left
    #: 9 of 260 random 2-3-box scenes with a label above 0.01 (none with 12; 12 band samples
    #: instead of 16: 6).
    residual_tail: int = 12
    #: With the tail samples: detached scan points per band or tail sample; each local extremum
    #: of ``B + R`` the scan finds claims a sample, in order (0: samples stay where
    #: :meth:`VSRDSilhouetteIntegrator._sub_sample` puts them); see
    #: :meth:`VSRDSilhouetteIntegrator._snapped_positions`.
    residual_tail_scan: int = 3
    #: With the residual search: exact residual values per band spaced over the enlarged box's
    #: chord, interpolated for the scans (0: every scan point evaluates the residual); see
    #: :meth:`VSRDSilhouetteIntegrator._chord_grid`. 0.5 resolved the residual at its
    #: initialisation, not a trained one, whose features are sharper than the encoding's highest
    #: frequency (``benchmarks/residual_trained.py`` on saved trained fields, s = 3: max 0.014 /
    #: 0.038 / 0.037 at 0.5, 0.008 / 0.012 / 0.017 at 0.35, 0.012 on one field evaluating the
    #: residual everywhere; step time 1.05-1.16x).
    residual_grid: float = 0.35
    #: With the chord grid: tabulate the residual per instance on a box-local lattice this many
    #: radians of the encoding's highest frequency apart when that is cheaper than evaluating it
    #: at every chord-grid point (dense ray batches), and fill the grids from it (0: never); see
    #: :meth:`VSRDSilhouetteIntegrator._residual_lattice`.
    residual_lattice: float = 0.35
    #: With the residual field: samples whose gradient vanishes (inside a monotone run of the
    #: scene SDF, one instance near) keep their values but leave the AD graph; see
    #: :meth:`VSRDSilhouetteIntegrator._frozen_lanes`.
    residual_sparse_gradients: bool = True
    #: Rays whose bands are isolated (see :meth:`VSRDSilhouetteIntegrator._isolated`) get
    #: ``isolated_band_samples`` band samples (>= 1; the first sits at the band's centre: the
    #: surface entry or closest approach) instead of ``band_samples``; with the residual field,
    #: the band's anchors and the extrema of ``B + R`` along it, where each band has at most
    #: ``isolated_extrema`` of them (see :meth:`VSRDSilhouetteIntegrator._extremum_samples`).
    isolated_rays: bool = True
    isolated_band_samples: int = 1
    isolated_extrema: int = 3
    ridge_gradients: bool = True
    coarse_samples: int = 100
    fine_samples: int = 100
    near: float = 0.0
    far: float = 100.0

    @staticmethod
    def from_props(props: mi.Properties) -> "SamplingConfig":
        d = SamplingConfig()
        cfg = SamplingConfig(
            sampling=str(props.get("sampling", d.sampling)),
            band_samples=int(props.get("band_samples", d.band_samples)),
            max_bands=int(props.get("max_bands", d.max_bands)),
            reach=float(props.get("reach", d.reach)),
            golden_iterations=int(props.get("golden_iterations", d.golden_iterations)),
            residual_scan=int(props.get("residual_scan", d.residual_scan)),
            residual_golden=int(props.get("residual_golden", d.residual_golden)),
            residual_tail=int(props.get("residual_tail", d.residual_tail)),
            residual_tail_scan=int(props.get("residual_tail_scan", d.residual_tail_scan)),
            residual_grid=float(props.get("residual_grid", d.residual_grid)),
            residual_lattice=float(props.get("residual_lattice", d.residual_lattice)),
            residual_sparse_gradients=bool(props.get("residual_sparse_gradients", d.residual_sparse_gradients)),
            isolated_rays=bool(props.get("isolated_rays", d.isolated_rays)),
            isolated_band_samples=int(props.get("isolated_band_samples", d.isolated_band_samples)),
            isolated_extrema=int(props.get("isolated_extrema", d.isolated_extrema)),
            ridge_gradients=bool(props.get("ridge_gradients", d.ridge_gradients)),
            coarse_samples=int(props.get("coarse_samples", d.coarse_samples)),
            fine_samples=int(props.get("fine_samples", d.fine_samples)),
            near=float(props.get("near", d.near)),
            far=float(props.get("far", d.far)),
        )
        if cfg.sampling not in ("adaptive", "dense"):
            raise ValueError(f"vsrd_silhouette: sampling must be 'adaptive' or 'dense', got {cfg.sampling!r}")
        if (cfg.band_samples < 2 or cfg.max_bands < 0 or cfg.coarse_samples < 2 or cfg.fine_samples < 1
                or cfg.residual_scan == 1 or cfg.residual_scan < 0 or cfg.residual_golden < 0
                or cfg.residual_tail < 0 or cfg.residual_tail_scan < 0 or cfg.residual_grid < 0 or cfg.residual_lattice < 0
                or cfg.isolated_band_samples < 1 or cfg.isolated_extrema < 0):
            raise ValueError("vsrd_silhouette: sample counts too small")
        if not (0.0 <= cfg.near < cfg.far):
            raise ValueError("vsrd_silhouette: need 0 <= near < far")
        return cfg


def instance_colours(n: int) -> list[tuple[float, float, float]]:
    """A fixed, distinguishable colour per instance (golden-angle hues)."""
    import colorsys
    return [colorsys.hsv_to_rgb((0.13 + 0.618034 * k) % 1.0, 0.75, 0.95) for k in range(n)]


class VSRDSilhouetteIntegrator(mi.ad.integrators.common.ADIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.field = InstanceField(props)
        self.cfg = SamplingConfig.from_props(props)
        self.sharpness = dr.opaque(mi.Float, float(props.get("sharpness", 10.0)))
        self.temperature = dr.opaque(mi.Float, float(props.get("temperature", 0.1)))
        #: Number of (sample, instance) SDF evaluations of the last call (for benchmarks/tests).
        self.last_stats: dict[str, int] = {}

    # -- Mitsuba plumbing ----------------------------------------------------------------------
    def traverse(self, cb: mi.TraversalCallback) -> None:
        self.field.traverse(cb)
        cb.put("sharpness", self.sharpness, mi.ParamFlags.NonDifferentiable)
        cb.put("temperature", self.temperature, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys: list[str]) -> None:
        for k in ("sharpness", "temperature"):
            v = getattr(self, k)
            if dr.width(v) != 1:
                raise ValueError(f"vsrd_silhouette: {k} must be a single value")
            dr.make_opaque(v)

    def set_schedule(self, sharpness: float, temperature: float) -> None:
        """Set ``s`` and ``tau`` without recompiling kernels."""
        self.sharpness = dr.opaque(mi.Float, float(sharpness))
        self.temperature = dr.opaque(mi.Float, float(temperature))

    def aov_names(self) -> list[str]:
        return [f"label_{k}" for k in range(self.field.n)] + ["background"]

    def to_string(self) -> str:
        return (f"VSRDSilhouetteIntegrator[instances={self.field.n}, sampling={self.cfg.sampling}, "
                f"residual={self.field.use_residual}]")

    def sample(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True, **kwargs):
        labels = self.render_rays(mi.Point3f(ray.o), mi.Vector3f(ray.d), mi.Float(ray.time))
        colours = instance_colours(self.field.n)
        rgb = mi.Color3f(0.0)
        for lab, c in zip(labels[:-1], colours):
            rgb += mi.Color3f(*c) * lab
        return mi.Spectrum(rgb), mi.Bool(active), labels, None

    # -- the integral --------------------------------------------------------------------------
    def render_rays(self, o: mi.Point3f, d: mi.Vector3f, time: mi.Float) -> list[mi.Float]:
        """Soft labels for a batch of rays (any cameras, per-ray frame offset ``time``).

        Returns ``N + 1`` Float arrays: one label per instance, then the background. Gradients
        flow to every differentiable parameter of :attr:`field`.
        """
        n_rays = dr.width(o.x)
        if self.field.n == 0:
            return [dr.ones(mi.Float, n_rays)]
        time = dr.detach(time)
        if dr.width(time) != n_rays:
            time = dr.full(mi.Float, time[0], n_rays)
        o, d = dr.detach(o), dr.detach(d)
        dec = self.field.decode()
        self.last_stats = {"rays": 0, "samples": 0, "sdf_evals": 0}
        if self.cfg.sampling == "dense":
            labels = self._render_dense(dec, o, d, time)
        else:
            labels = self._render_adaptive(dec, o, d, time)
        if labels is None:  # no ray meets any (enlarged) box
            return [dr.zeros(mi.Float, n_rays) for _ in range(self.field.n)] + [dr.ones(mi.Float, n_rays)]
        total = labels[0]
        for lab in labels[1:]:
            total = total + lab
        return labels + [1.0 - total]

    def _count(self, rays: int, samples_per_ray: int, instances: int) -> None:
        for key, v in (("rays", rays), ("samples", rays * samples_per_ray),
                       ("sdf_evals", rays * samples_per_ray * instances)):
            self.last_stats[key] += v

    def _render_dense(self, dec, o, d, time) -> list[mi.Float]:
        """Every instance at every one of the ``coarse + fine`` samples of every ray."""
        n_rays = dr.width(o.x)
        t, m = self._dense_positions(dec, o, d, time)
        labels = self.integrate_at(dec, dr.arange(mi.UInt32, n_rays), o, d, time, t, m)
        self._count(n_rays, m, self.field.n)
        return labels

    def _render_adaptive(self, dec, o, d, time) -> list[mi.Float] | None:
        """Band samples of the rays that meet an enlarged box; at each sample only the instances
        whose enlarged box the ray meets (one SDF evaluation per lane and met instance)."""
        n_rays, n_inst = dr.width(o.x), self.field.n
        bands = self._adaptive_bands(dec, o, d, time)
        grid = bands[-1]
        groups = list(self._adaptive_groups(dec, o, d, time, bands))
        if not groups:
            return None
        # one flat list of (point, time, instance) lanes for every group and band slot, so the
        # SDF (and the residual MLP) is evaluated in one batch
        with dr.suspend_grad():
            # per group the pieces (one per band slot, one for an isolated group)
            ray_lanes, ts, insts, deep, pairs = [], [], [], [], []
            kink_lams = []  # per lane, as deep: a kink's own weight (-1: none)
            for rays, t, m, _, slot_inst, deepest, _, own, rows, kink_lam, _ in groups:
                r = dr.arange(mi.UInt32, dr.width(t)) // m
                ray_of = dr.gather(mi.UInt32, rays, r)
                # an isolated group's samples evaluate their own band's instance only
                bands_of = [own] if own is not None else [mi.UInt32(b) for b in range(len(slot_inst))]
                if grid is not None:  # each lane's (slot, ray) pair of the chord grid
                    row_of = dr.gather(mi.UInt32, rows, r)
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
                deep.append([dr.select(deepest == b, 1, 0) for b in bands_of])
                kink_lams.append([dr.select(deepest == b, kink_lam, -1.0) for b in bands_of])
            ray_all = concat_groups(ray_lanes)
            s_all = concat_groups(ts)
            p_all, t_all, d_all = self._positions(ray_all, o, d, time, s_all, 1)
            i_all = concat_groups(insts)
            # lanes at the deepest point of their ray in their instance's box, or at a kink of
            # it where B + R has a minimum (ridge gradients; a kink with its own weight)
            deep = dr.compress(concat_groups(deep) > 0)
            ridge = None
            if self.cfg.ridge_gradients and dr.width(deep):
                ridge = (deep, dr.gather(mi.Vector3f, d_all, deep), RIDGE_TOLERANCE,
                         dr.gather(mi.Float, concat_groups(kink_lams), deep))
        # beyond the culling margin of its box a lane's SDF cannot move the integral by more
        # than exp(-reach) (see _cull_margin): its value is kept, its gradient dropped
        weights = self.field.residual_weights()
        kw = dict(reach=self._residual_reach(), grad_reach=dr.detach(self._cull_margin()))
        values = frozen = None
        if weights is not None and self.cfg.residual_sparse_gradients:
            with dr.suspend_grad():
                if grid is not None:
                    values = self._grid_values(dec, grid, concat_groups(pairs), s_all, p_all, t_all, i_all,
                                               groups, deep, weights, kw)
                else:
                    values = self.field.lane_sdfs(dec, p_all, t_all, i_all, weights, **kw)
                frozen = self._frozen_lanes(values, groups, deep)
        f_all = self.field.lane_sdfs(dec, p_all, t_all, i_all, weights, ridge=ridge, values=values,
                                     frozen=frozen, **kw)
        flat = dr.zeros(mi.Float, n_rays * n_inst)
        start = 0
        for rays, t, m, active, slot_inst, _, peak, own, _, _, real in groups:
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
            # sample (see _isolated): it is left out of the minimum and the softmin there
            sdfs = slices if own is None else [dr.select(own == b, slices[0], ISOLATED_ELSEWHERE)
                                               for b in range(len(slot_inst))]
            for lab, ib in zip(self._integrate(sdfs, m, peak if self.cfg.ridge_gradients else None), slot_inst):
                dr.scatter_add(flat, lab, rays * n_inst + ib, active)
            self._count(real, m, len(slices))
        idx = dr.arange(mi.UInt32, n_rays) * n_inst
        return [dr.gather(mi.Float, flat, idx + k) for k in range(n_inst)]

    def _grid_values(self, dec, grid: ChordGrid, pairs: mi.UInt32, s: mi.Float, p: mi.Point3f, time: mi.Float,
                     inst: mi.UInt32, groups: list[SampleGroup], deep: mi.UInt32, weights, kw: dict) -> mi.Float:
        """Detached SDF values of :meth:`_render_adaptive`'s lanes (``pairs``: each lane's (slot,
        ray) pair of ``grid``; ``s``: its ray parameter; ``p``, ``time``, ``inst``: its point,
        ray time and instance) for :meth:`_frozen_lanes`: ``B`` exact and ``R`` interpolated from
        the chord grid, exact where it can matter.

        A frozen lane's value drops out of the integral (it lies strictly inside a monotone run
        of ``f``, whose opacity telescopes to the run's ends), as long as it keeps the run
        monotone; the lanes that keep their gradient are the run's ends and get exact values in
        the AD graph. So the interpolated values sort the lanes with a margin of
        :data:`GRID_TOLERANCE` (above the interpolation error: p99 5e-5 m, p9999 9e-4 m at the
        samples), the lanes that stay in the graph under it and their neighbours (whose order
        against them decides where a run ends) get exact values, and :meth:`_render_adaptive`
        sorts the lanes again with them. With the plain margin a shallow extremum of the
        exact ``B + R`` that the interpolation smooths out stayed frozen: sparse vs full-graph
        box gradient 4.2e-2 relative on the benchmark's 3-box scene, now 3.4e-4 (exact values
        everywhere: 6.8e-4; ``test_residual_grid_keeps_the_sparse_gradient``). 6 boxes / 16k
        rays: 0.26M exact residuals instead of 1.06M.
        """
        values, box = grid.sdf_within(pairs, s, kw["reach"])
        dr.eval(values, box)  # one kernel for both
        frozen = self._frozen_lanes(values, groups, deep, GRID_TOLERANCE)
        # beyond the reach a value is the exact B already (a margin keeps the lanes whose B the
        # world-frame evaluation of lane_sdfs could put on the other side of the reach)
        border = self._run_ends(frozen, groups) & (box <= kw["reach"] + REACH_ROUNDING)
        idx = dr.compress(border)
        if dr.width(idx):
            exact = self.field.lane_sdfs(dec, dr.gather(type(p), p, idx), dr.gather(mi.Float, time, idx),
                                         dr.gather(mi.UInt32, inst, idx), weights, **kw)
            dr.scatter(values, exact, idx)
        dr.eval(values)
        return values

    @staticmethod
    def _run_ends(frozen: mi.Bool, groups: list[SampleGroup]) -> mi.Bool:
        """Lanes of :meth:`_render_adaptive`'s flat layout that are not ``frozen``
        (:meth:`_frozen_lanes`) or neighbour such a lane along their ray."""
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

    def _frozen_lanes(self, values: mi.Float, groups: list[SampleGroup], deep: mi.UInt32,
                      tolerance: float = MONOTONE_TOLERANCE) -> mi.Bool:
        """Lanes of :meth:`_render_adaptive`'s flat layout whose SDF value cannot carry a
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
        margin = dr.detach(self._cull_margin())
        s = dr.detach(self.sharpness)
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
            log_t, _ = self._log_transmittance(s, f, f_after, j == m - 1, m)
            shadowed = (j > 0) & (dr.gather(mi.Float, log_t, dr.select(j > 0, lane - 1, lane)) < -self.cfg.reach)
            free |= shadowed
            for b in range(n_slots):
                dr.scatter(frozen, free, lane + dr.opaque(mi.UInt32, start + b * w))
            start += w * n_slots
        if dr.width(deep):
            dr.scatter(frozen, False, deep)
        return frozen

    def _reach(self) -> mi.Float:
        """Band half-width ``reach / s`` in scene units."""
        return self.cfg.reach / self.sharpness

    def _cull_margin(self) -> mi.Float:
        """Box SDF value beyond which an instance is dropped from a ray: ``reach * max(1/s, tau)``.

        Past it both its opacity (``Phi_s``) and its softmin label share next to a surface are
        below ``exp(-reach)``."""
        return self.cfg.reach * dr.maximum(1.0 / self.sharpness, self.temperature)

    def _residual_reach(self) -> mi.Float:
        """Where the residual is evaluated: inside boxes enlarged by the culling margin (an opaque
        Float: a literal would recompile whenever s changes). ``R >= 0``, so where the box SDF is
        beyond the margin ``B + R`` is too, and the residual cannot move the integral there by
        more than the culling bound. Enlarging by the residual's own reach ``r_max`` as well
        (1 m) evaluated the MLP at 1.4x the points and widened the bands for nothing."""
        return dr.detach(self._cull_margin())

    @staticmethod
    def _positions(ray_idx: mi.UInt32, o, d, time, t: mi.Float, m: int):
        """Sample points ``o + t d``, their ray times and directions for ``m`` samples per ray
        (detached)."""
        n = dr.width(ray_idx)
        with dr.suspend_grad():
            r = ray_idx if m == 1 else dr.gather(mi.UInt32, ray_idx, dr.arange(mi.UInt32, n * m) // m)
            dirs = dr.gather(mi.Vector3f, d, r)
            return dr.gather(mi.Point3f, o, r) + t * dirs, dr.gather(mi.Float, time, r), dirs

    def integrate_at(self, dec, ray_idx: mi.UInt32, o, d, time, t: mi.Float, m: int) -> list[mi.Float]:
        """Labels of rays ``ray_idx`` from the NeuS integral at given sorted samples ``t``
        (``m`` per ray): the integral both strategies use, for references and tests."""
        p, tg, dirs = self._positions(ray_idx, o, d, time, t, m)
        sdfs = self.field.instance_sdfs(dec, p, tg, self.field.residual_weights(), reach=self._residual_reach())
        return self._integrate(self._ridge_gradients(dec, sdfs, p, tg, dirs, t, m), m)

    def _ridge_gradients(self, dec, sdfs: list[mi.Float], p, time, dirs, t: mi.Float, m: int) -> list[mi.Float]:
        """Give each ray's deepest sample inside each box the envelope gradient of the box's
        minimum along the ray (:func:`~vsrd_plugins.sdf.box_sdf_ray_local`), as the adaptive
        sampler does at its exact deepest point: the sampled minimum stands in for the true one,
        within a face tolerance of twice the local sample spacing (slopes are at most 1)."""
        if not self.cfg.ridge_gradients:
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
            out.append(f + self.field.ridge_correction(dec, p, time, mi.UInt32(k), ridge))
        return out

    def _integrate(self, sdfs: list[mi.Float], m: int,
                   peak: tuple[mi.UInt32, mi.UInt32, mi.Float] | None = None) -> list[mi.Float]:
        """Differentiable NeuS integral of instance SDFs at ``m`` sorted samples per ray
        (``peak``: per lane the indices ``a, b`` of two instances crossing at a gap peak and the envelope
        weight of ``a``, ``-1`` for none, see :meth:`_gap_peaks`)."""
        n = dr.width(sdfs[0]) // m
        with dr.suspend_grad():
            lane = dr.arange(mi.UInt32, n * m)
            last = (lane % m) == (m - 1)
        # every instance's SDFs (and their adjoints in the reverse pass) in one kernel
        sdfs = dr.custom(_EvalTogether, sdfs)
        f = scene_sdf(sdfs)
        if peak is not None and len(sdfs) > 1:
            f = self._crossing_gradient(f, sdfs, *peak)
        s = self.sharpness
        nexts = dr.custom(_NextSample, sdfs, m)
        f_next = scene_sdf(nexts)
        w, log1ma = self._interval_weights(s, f, f_next, last, m)
        labels = None
        for theta in self._accrual_quantiles(s, f, f_next, log1ma):
            at = dr.custom(_EvalTogether, [a + (b - a) * theta for a, b in zip(sdfs, nexts)])
            lab = softmin_labels(at, self.temperature)
            labels = lab if labels is None else [x + y for x, y in zip(labels, lab)]
        w_point = w * (1.0 / len(GAUSS_QUANTILES))  # equal Gauss-Legendre weights
        terms = [w_point * lab for lab in labels]
        # one kernel for every instance's terms: block_sum of an unevaluated array evaluates it
        # alone, recomputing the shared weights once per instance
        dr.eval(terms)
        return [dr.block_sum(x, m) for x in terms]

    @staticmethod
    def _log_transmittance(s, f, f_next, last: mi.Bool, m: int) -> tuple[mi.Float, mi.Float]:
        """``log T_i`` (before the interval from each sample to the next) and ``log(1 -
        alpha_i)`` of the NeuS opacity in log space (module docstring; ``m`` samples per ray,
        ``last`` marks each ray's last sample, which starts no interval)."""
        log1ma = dr.select(last, 0.0, dr.minimum(softplus(-s * f) - softplus(-s * f_next), 0.0))
        return dr.block_prefix_sum(log1ma, m, exclusive=True), log1ma

    @staticmethod
    def _interval_weights(s, f, f_next, last: mi.Bool, m: int) -> tuple[mi.Float, mi.Float]:
        """NeuS weights ``w_i = T_i alpha_i`` of the intervals between each sample and the next
        and ``log(1 - alpha_i)`` (:meth:`_log_transmittance`)."""
        log_t, log1ma = VSRDSilhouetteIntegrator._log_transmittance(s, f, f_next, last, m)
        return dr.exp(log_t) - dr.exp(log_t + log1ma), log1ma

    @staticmethod
    def _crossing_gradient(f: mi.Float, sdfs: list[mi.Float], a: mi.UInt32, b: mi.UInt32,
                           lam: mi.Float) -> mi.Float:
        """Scene SDF ``f`` whose gradient at gap-peak lanes (where the instances of bands ``a``
        and ``b`` cross and are the minimum) is the envelope blend with weight ``lam``."""
        fa, fb = sdfs[0], sdfs[0]
        for k in range(1, len(sdfs)):
            fa, fb = dr.select(a == k, sdfs[k], fa), dr.select(b == k, sdfs[k], fb)
        with dr.suspend_grad():
            da, db, df = dr.detach(fa), dr.detach(fb), dr.detach(f)
            ok = ((lam >= 0.0) & (dr.abs(da - db) <= RIDGE_TOLERANCE) & (dr.minimum(da, db) <= df))
        return dr.select(ok, envelope_blend(f, fa, fb, lam), f)

    @staticmethod
    def _accrual_quantiles(s, fa, fb, log1ma) -> tuple[mi.Float, ...]:
        """Positions ``theta`` in [0, 1] where an interval has accrued the fractions ``q = 1/2 -+
        1/(2 sqrt 3)`` of its opacity: the two-point Gauss-Legendre rule in ``q`` for the
        opacity-weighted label ``int softmin(F(theta(q))) dq``.

        With ``f`` linear over the interval, ``Phi(s f(theta)) = Phi(s fa) (1 - q alpha)`` at
        the ``q`` quantile, so ``s f = L - log(Phi(-s fa) + Phi(s fa) q alpha)`` with ``L = log
        Phi(s fa) + log(1 - q alpha)`` (both terms positive: no cancellation). Intervals with
        negligible opacity or a flat ``f`` use the quantiles of a uniform weight.

        Interpolating the instance SDFs there, not the endpoint labels, keeps a label switch
        between two boxes inside a long interval where their SDFs cross. Against one point at
        the opacity-weighted mean position, labels vs the reference (K = 16, slow-test scenes):
        12 boxes at s = 3 max 0.0114 -> 0.0087, 3 boxes at s = 10 0.0078 -> 0.0040; bench 6 boxes
        max 0.0016 -> 0.0007, at the same step time.
        """
        alpha = 1.0 - dr.exp(log1ma)
        df = fb - fa
        ok = ((alpha > ACCRUAL_MIN_OPACITY) & (dr.abs(s * df) > ACCRUAL_MIN_SLOPE)
              & (s * fa > -ACCRUAL_MAX_DEPTH))
        sfa = s * fa
        log_phi_a = -softplus(-sfa)
        phi_a, phi_na = dr.exp(log_phi_a), dr.exp(-softplus(sfa))
        sdf_ = s * dr.select(ok, df, 1.0)
        out = []
        for q in GAUSS_QUANTILES:
            qa = q * dr.select(ok, alpha, 0.5)
            sf = log_phi_a + dr.log(1.0 - qa) - dr.log(phi_na + phi_a * qa)
            theta = (sf - sfa) / sdf_
            out.append(dr.select(ok, dr.clip(theta, 0.0, 1.0), q))
        return tuple(out)

    # -- dense (reference) sampling ------------------------------------------------------------
    def _dense_positions(self, dec, o, d, time) -> tuple[mi.Float, int]:
        """Coarse stratified + importance samples, merged in order (detached)."""
        cfg = self.cfg
        nc, nf = cfg.coarse_samples, cfg.fine_samples
        n = dr.width(o.x)
        with dr.suspend_grad():
            lane = dr.arange(mi.UInt32, n * nc)
            r, i = lane // nc, lane % nc
            step = (cfg.far - cfg.near) / (nc - 1)
            tc = cfg.near + mi.Float(i) * step
            p = dr.gather(mi.Point3f, o, r) + tc * dr.gather(mi.Vector3f, d, r)
            tg = dr.gather(mi.Float, time, r)
            f = scene_sdf(self.field.instance_sdfs(dec, p, tg, self.field.residual_weights(),
                                                   reach=self._residual_reach()))
            last = i == (nc - 1)
            f_next = dr.gather(mi.Float, f, block_successor(n * nc, nc))
            w, _ = self._interval_weights(self.sharpness, f, f_next, last, nc)
            # pdf over the nc - 1 intervals; a uniform floor guards rays whose weights vanish
            # (the reference divides by ~1e-6 there and sends samples to 1e6 m).
            total = dr.block_sum(w, nc)
            floor = 1e-3 * dr.maximum(dr.gather(mi.Float, total, r), 1e-8) / (nc - 1)
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

    # -- adaptive sampling ---------------------------------------------------------------------
    def _adaptive_bands(self, dec, o, d, time):
        """Detached per-ray band search.

        Returns ``(ray_idx, count, slots, slot_inst, slot_hit, isolated)``: indices of rays meeting at least
        one enlarged box, their number of bands, per slot a :class:`Slot` of arrays over those
        rays (the gap peak after the band with its crossing slots and envelope weight, see
        :meth:`_gap_peaks`; the end of the second tail, see :meth:`_tail_samples`; the sample at
        a hit's minimum, ``extra`` unless the band already ends there; slots sorted by the box's
        deepest point / closest approach along the ray, which :meth:`_gap_peaks` needs; a ray's
        valid slots come first), per slot the band's
        instance (``num_instances`` for an empty slot) and whether the ray enters that box, and
        per ray whether it is isolated (:meth:`_isolated`).
        """
        cfg = self.cfg
        n_inst = self.field.n
        n = dr.width(o.x)
        big = 1e30
        with dr.suspend_grad():
            w = self._reach()
            margin = self._cull_margin()
            views, entry, exit_, hit, tin, tout, act = [], [], [], [], [], [], []
            for k in range(n_inst):
                bv = self.field.view(dec, k, time, n)
                ol, dl = bv.to_local(o), bv.dir_to_local(d)
                e0, e1 = ray_box_interval(ol, dl, bv.half + margin)
                e0, e1 = dr.maximum(e0, cfg.near), dr.minimum(e1, cfg.far)
                b0, b1 = ray_box_interval(ol, dl, bv.half)
                views.append((ol, dl, bv.half))
                entry.append(e0)
                exit_.append(e1)
                act.append(e0 < e1)
                hit.append((b0 <= b1) & (b1 > cfg.near) & (b0 < cfg.far))
                tin.append(dr.maximum(b0, cfg.near))
                tout.append(dr.minimum(b1, cfg.far))
            any_act, met = act[0], dr.select(act[0], 1, 0)
            for a in act[1:]:
                # not ``|=``: Dr.Jit's in-place operators update the array object itself, which
                # is act[0] (instance 0 then met every ray that met any box)
                any_act = any_act | a
                met = met + dr.select(a, 1, 0)
            # one kernel for every per-instance ray quantity (a gather from an unevaluated
            # array evaluates it alone: 10 small kernels per instance)
            dr.eval(any_act, met, views, entry, exit_, act, hit, tin, tout)
            ray_idx = dr.compress(any_act)
            if dr.width(ray_idx) == 0:
                return ray_idx, None, [], [], [], None, None
            # slots (and gaps between them) only up to the most boxes a ray meets: their
            # searches run for every ray. Kernels are shaped by this count (at most one set per
            # count, compiled once each)
            most_met = int(dr.max(met)[0])

            def sel(x, ty=mi.Float):
                return dr.gather(ty, x, ray_idx)

            views = [tuple(sel(v, type(v)) for v in vw) for vw in views]
            entry = [sel(x) for x in entry]
            exit_ = [sel(x) for x in exit_]
            act = [sel(x, mi.Bool) for x in act]
            hit = [sel(x, mi.Bool) for x in hit]
            tin = [sel(x) for x in tin]
            tout = [sel(x) for x in tout]

            # golden-section search for argmin_t B_k(o + t d) on [entry, exit] (B_k is convex)
            def fk(k):
                ol, dl, half = views[k]
                return lambda t: box_sdf_local(ol + t * dl, half)

            tstar = golden_section([fk(k) for k in range(n_inst)], list(zip(entry, exit_)),
                                   cfg.golden_iterations, "vsrd_golden_section")

            # per instance band: hits centre on the entry, misses end at the closest approach
            centre = [dr.select(hit[k], tin[k], tstar[k]) for k in range(n_inst)]
            keys = [dr.select(act[k], tstar[k], big) for k in range(n_inst)]
            count = mi.UInt32(0)
            picked, slot_inst = [], []
            n_slots = min(most_met, n_inst if cfg.max_bands <= 0 else cfg.max_bands)
            for _ in range(n_slots):
                best = mi.Float(big)
                kb = mi.UInt32(n_inst)
                for k in range(n_inst):
                    better = keys[k] < best
                    best = dr.select(better, keys[k], best)
                    kb = dr.select(better, k, kb)
                valid = best < big
                count += dr.select(valid, 1, 0)
                e0, e1, ts, c, b1 = [mi.Float(0.0)] * 5
                hb = mi.Bool(False)
                for k in range(n_inst):
                    is_k = kb == k
                    e0, e1, ts, c, b1 = [dr.select(is_k, v, vv) for v, vv in
                                         zip((entry[k], exit_[k], tstar[k], centre[k], tout[k]), (e0, e1, ts, c, b1))]
                    hb = dr.select(is_k, hit[k], hb)
                    keys[k] = dr.select(is_k, big, keys[k])
                picked.append(Picked(valid, e0, e1, ts, c, b1, hb))
                slot_inst.append(kb)
            slot_views = [self._slot_view(views, kb) for kb in slot_inst]
            # the picked boxes and their views in one kernel (read per slot below)
            dr.eval(count, slot_inst, picked, slot_views)
            # with the residual the instance SDF B + R has its minimum near, not at, the box's:
            # the band ends there instead (the gap peaks and the slot order stay the box's)
            fmin = sdf = grid = None
            if self._residual_search():  # F = B + R of every (slot, ray) pair, built once
                if cfg.residual_grid > 0:
                    grid = self._chord_grid(dec, slot_views, slot_inst, count, picked)
                    # the grid's valid pairs (no second compress: it costs a host round trip)
                    sdf = PairScan(grid.points > 0, grid.pairs, grid.rank, grid.sdf, traceable=True)
                else:
                    sdf = PairScan.of(concat([count > b for b in range(len(slot_inst))]),
                                      self._pair_sdf(slot_views, slot_inst))
                fmin = self._residual_minima(sdf, slot_views, count, picked)
            use_tail = self._tail_samples()[1] > 0
            anchors, slot_hit, slot_ts, tails, deepests = [], [], [], [], []
            for b, pk in enumerate(picked):
                valid, e0, e1, ts, c, hb = pk.valid, pk.entry, pk.exit, pk.tstar, pk.centre, pk.hit
                if fmin is not None:
                    c = dr.select(hb, c, fmin[b])
                    ts_band = fmin[b]
                else:
                    ts_band = ts
                # two-sided band around c, covering the descent in f from the enlarged box's
                # entry (f >= w there) to c: hits then run to c + w and the deepest point,
                # misses to the enlarged box's exit (f >= w again). Spaced in t, crowding mildly
                # towards c (see _sub_sample), which is close to uniform in f for a box; grazing
                # rays get long but complete bands.
                lo = e0
                mid = dr.maximum(c, lo)
                # with a tail (residual only) a band's second half ends a reach after its
                # minimum, misses included, and the tail runs from there to the enlarged box's
                # exit: B + R can dip again anywhere along the chord
                far_end = dr.minimum(c + w, e1) if use_tail else e1
                hi = dr.maximum(dr.select(hb, dr.minimum(c + w, dr.maximum(ts_band, c)), far_end), mid)
                extra = dr.maximum(dr.select(hb, ts_band, far_end), hi)
                tail, deepest_t = extra, extra
                if use_tail:
                    tail = dr.maximum(e1, extra)
                    # where the band already ends at its minimum (a miss: at its centre; a hit
                    # whose least B + R lies within a reach of its entry: at its last sample),
                    # the first tail would sit on one point: the extra sample then splits the
                    # rest of the chord between the two tails instead (and is no deepest point)
                    split = extra <= hi
                    deepest_t = dr.select(split, hi, extra)
                    extra = dr.select(split, dr.maximum(0.5 * (hi + tail), hi), extra)
                    mid, hi, extra, deepest_t = self._lengthwise_miss(hb, e0, c, mid, hi, extra, tail, deepest_t)
                anchors.append([dr.select(valid, v, cfg.far) for v in (e0, lo, mid, hi, extra)])
                deepests.append(dr.select(valid, deepest_t, cfg.far))
                tails.append(dr.select(valid, tail, cfg.far))
                slot_hit.append(valid & hb)
                slot_ts.append(dr.select(valid, ts, cfg.far))
            # every slot's anchors in one kernel: the searches and scans below read them per
            # slot (a concatenation scatters each alone), which evaluated each anchor in a kernel
            # of its own, recomputing the slot selection every time
            dr.eval(anchors, deepests, tails, slot_hit, slot_ts)
            peaks = self._gap_peaks(slot_views, slot_ts, count)
            if sdf is not None:  # with the residual the boxes' instance SDFs cross elsewhere
                peaks = self._residual_peaks(sdf, peaks, slot_ts, self._residual_reach())
            slots = [Slot(*anchor, peak=dr.select(pk.ok, pk.t, anchor[4]),
                          peak_lambda=dr.select(pk.ok, pk.lam, -1.0), peak_a=pk.a, peak_b=pk.b,
                          tail_end=tail, deepest=deep)
                     for anchor, pk, tail, deep in zip(anchors, peaks, tails, deepests)]
            if self._snaps():  # band and tail samples at the extrema of B + R
                # the kinks of each hit box's B along the ray: where B + R can have a minimum
                # that a parabola through scan points misses
                # (per (slot, ray) pair, slot-major: one kernel for every slot)
                views = grid.views if grid is not None else self._pair_views(slot_views)
                valid, hit = concat([pk.valid for pk in picked]), concat([pk.valid & pk.hit for pk in picked])
                kinks = box_ray_kinks(*views, dr.select(hit, concat([pk.centre for pk in picked]), 0.0),
                                      dr.select(hit, concat([pk.surface_exit for pk in picked]), -1.0))
                bends = box_ray_bends(*views, dr.select(valid, concat([pk.entry for pk in picked]), 0.0),
                                      dr.select(valid, concat([pk.exit for pk in picked]), -1.0))
                minima = self._kink_minima(sdf, kinks, bends, 1.0 / self._residual_omega())
                slots = [replace(sl, kinks=tuple(block_of(x, b, dr.width(count)) for t, _, lam in minima for x in (t, lam)))
                         for b, sl in enumerate(slots)]
            isolated = self._isolated(picked, count)
            if self._isolates() and grid is not None:
                # with the residual field an isolated ray keeps its layout only where its bands
                # have few extrema of B + R (each of them a sample), and where enough rays do
                isolated, worth = self._worth_isolating(isolated, count, len(slots))
                if worth:
                    extrema, found = self._chord_extrema(grid, concat([pk.valid & isolated for pk in picked]),
                                                         [t for t, _, _ in minima])
                    n = dr.width(count)
                    for b, sl in enumerate(slots):
                        isolated = isolated & ((count <= b) | (block_of(found, b, n) <= self.cfg.isolated_extrema))
                        slots[b] = replace(sl, isolated=self._extremum_samples(sl, [block_of(x, b, n) for x in extrema]))
                    isolated, _ = self._worth_isolating(isolated, count, len(slots))
                    # the moved samples of the full layout: only the other rays' pairs scan for them
                    sdf = PairScan.of((grid.points > 0) & ~concat([isolated] * len(picked)), grid.sdf, traceable=True)
            if self._snaps() and dr.width(sdf.pairs):  # (none: every ray is isolated)
                slots = [replace(sl, moved=tuple(x for part in parts for x in part))
                         for sl, parts in zip(slots, zip(*self._snapped_slots(sdf, slots, minima)))]
            dr.eval(count, slots, slot_inst, slot_hit, isolated)
        return ray_idx, count, slots, slot_inst, slot_hit, isolated, grid

    def _lengthwise_miss(self, hit: mi.Bool, e0: mi.Float, c: mi.Float, mid: mi.Float, hi: mi.Float,
                         extra: mi.Float, tail: mi.Float, deepest: mi.Float) -> tuple[mi.Float, ...]:
        """With the tail samples, the anchors ``(mid, hi, extra, deepest)`` of a miss band whose
        least ``B + R`` ``c`` lies far into its chord ``[e0, tail]``.

        A miss band normally ends its first half at ``c`` (``k1 = K/2`` cells from the enlarged
        box's entry), and its second half and the two tails share the rest of the chord. A ray
        that grazes the box lengthwise and leaves it soon after its least ``B + R`` then has
        ``k1`` wide cells before ``c``, where ``B + R`` can have further extrema that a cell's one
        movable sample cannot all take, and its tails stack on the chord's end (integrator
        tests' random 2-3-box residual scenes: labels off by up to 0.0135). Such a band puts
        ``c`` at its extra sample instead, with the ``K + T/2 + 1`` cells of the band and the
        first tail spread evenly before it and the second tail after it; of the two layouts it
        takes the one whose widest cell is narrower. 112 random 2-3-box scenes (256 rays each):
        rays above 0.01 in 7 -> 6 scenes, mean of the scenes' max error 0.0054 -> 0.0052; it can
        cost accuracy where another box's band overlaps the shortened side (one scene < 0.008 ->
        0.0107). The worst scene (0.0294, unchanged) is a hit whose tail cell inside the box
        holds a maximum and a minimum of ``B + R``."""
        k1, k2 = self._halves(self.cfg.band_samples)
        kp, kq = self._tail_samples()
        before, after = dr.maximum(c - e0, 0.0), dr.maximum(tail - c, 0.0)
        n_before = k1 + k2 + kp + 1
        widest_now = dr.maximum(dr.maximum(before * (1.0 / k1), (hi - mid) * (1.0 / k2)),
                                (tail - hi) * (1.0 / (kp + 1 + kq)))
        widest_lengthwise = dr.maximum(before * (1.0 / n_before), after * (1.0 / kq))
        lengthwise = ~hit & (widest_lengthwise < widest_now)
        return (dr.select(lengthwise, dr.fma(before, k1 / n_before, e0), mid),
                dr.select(lengthwise, dr.fma(before, (k1 + k2) / n_before, e0), hi),
                dr.select(lengthwise, c, extra), dr.select(lengthwise, c, deepest))

    def _isolated(self, picked: list[Picked], count: mi.UInt32) -> mi.Bool:
        """Rays whose enlarged-box intervals are pairwise disjoint (none when ``isolated_rays``
        is off; with the residual field :meth:`_adaptive_bands` keeps only those whose bands have
        few extrema of ``B + R``, :meth:`_chord_extrema`).

        Then at every sample of a band every other instance lies beyond its culling margin, so
        its softmin share is below ``exp(-reach)`` and the band's labels are its opacity; and
        the opacity telescopes exactly over each monotone stretch of the (convex) box SDF, whose
        ends the band already samples: the enlarged box's entry, the surface entry or closest
        approach, the deepest point, and the gap peaks. Such a band needs no more samples in
        between (``isolated_band_samples``, default 1: the enlarged box's entry, the surface
        entry or closest approach, the deepest point or the enlarged box's exit, and the peak
        slot, a copy of the latter, per band). Slots are sorted by
        closest approach, which lies in each interval, so checking consecutive slots suffices.
        """
        if not self._isolates():
            return mi.Bool(False)
        isolated = mi.Bool(True)
        for b in range(len(picked) - 1):
            exit_b, entry_next = picked[b].exit, picked[b + 1].entry
            isolated &= (count <= b + 1) | (exit_b < entry_next)
        return isolated

    def _isolates(self) -> bool:
        """Whether isolated rays get their own layout: ``isolated_rays`` is on and either the
        residual field is off or the extrema of ``B + R`` are searched (moved samples and the
        chord grid on: ``B + R`` need not be convex along a ray, and the isolated layout samples
        its extrema, :meth:`_extremum_samples`)."""
        return self.cfg.isolated_rays and (self.field.residual_reach == 0
                                           or (self._snaps() and self.cfg.residual_grid > 0))

    def _worth_isolating(self, isolated: mi.Bool, count: mi.UInt32, n_slots: int) -> tuple[mi.Bool, bool]:
        """With the residual field, ``isolated`` where the batch's isolated rays together pay for
        their sample groups, else no ray, and which of the two: a group costs a fixed
        :data:`GROUP_COST_SAMPLES` on top of its samples, and an isolated band saves the full
        layout's samples minus its own (:meth:`_extremum_samples`). (6 boxes, 1000 rays: 10 %
        slower with the isolated rays in groups of their own; 16k rays 25 % faster.) Decided
        for the batch as a whole, not per band count: a band count whose isolated group came
        and went from step to step compiled its kernels at the first step it came.
        """
        saved_per_band = self._band_layout(False, self.cfg.band_samples)[1] - self._band_layout(True)[1]
        hist = dr.zeros(mi.UInt32, n_slots + 1)
        dr.scatter_add(hist, mi.UInt32(isolated), count)
        rays = hist.numpy()[1:].astype(np.int64)
        saved = int((rays * np.arange(1, n_slots + 1)).sum()) * saved_per_band
        worth = saved >= GROUP_COST_SAMPLES * int((rays > 0).sum()) and saved > 0
        return (isolated if worth else dr.zeros(mi.Bool, dr.width(count))), worth

    def _band_layout(self, extrema: bool, kk: int = 0) -> tuple[int | None, int]:
        """Per band of :meth:`_adaptive_groups`: the index of its extra sample and its samples,
        the gap peak included. The full layout: entry, ``kk`` band samples, the first tail, the
        extra sample, the second tail, the peak (:meth:`_tail_samples`). An isolated band with
        the residual field (``extrema``): entry, :attr:`Slot.isolated` (the extra sample among
        them: index ``None``), the peak."""
        if extrema:
            return None, 1 + len(ISOLATED_ANCHORS) + self.cfg.isolated_extrema + KINK_MINIMA + 1
        kp, kq = self._tail_samples()
        j_ex = kk + kp + 1
        return j_ex, j_ex + kq + 2

    def _extremum_samples(self, sl: Slot, extrema: list[mi.Float]) -> tuple:
        """An isolated ray's samples of a band after its entry, with the residual field: its
        anchors (:data:`ISOLATED_ANCHORS`), the extrema of ``B + R`` along the chord
        (:meth:`_chord_extrema`; ``-1``: none) and its minima at kinks and bends of ``B``
        (:attr:`Slot.kinks`, :meth:`_kink_minima`; :data:`KINK_MINIMA` of them), sorted (the
        exit stands in for missing ones).

        On an isolated ray every other box is beyond its culling margin at the band's samples,
        so the labels are the band's opacity, which telescopes over each monotone run of ``F =
        B + R``: it depends on ``F`` at the run ends alone. Those are the chord's ends, the least
        ``F`` and the extrema, which these samples hold.
        """
        kink_ts = list(sl.kinks[0::2])
        return tuple(sorted_arrays([*(getattr(sl, name) for name in ISOLATED_ANCHORS),
                                    *(dr.select(x >= 0.0, x, sl.tail_end) for x in (*extrema, *kink_ts))]))

    def _chord_extrema(self, grid: "ChordGrid", scan: mi.Bool, kinks: list[mi.Float]) -> tuple[list[mi.Float], mi.UInt32]:
        """Per (slot, ray) pair of ``grid`` where ``scan`` holds: the first ``isolated_extrema``
        local extrema of ``F = B + R`` along its chord (``-1`` past the last) and how many there
        are (detached; 0 and ``-1`` elsewhere). ``kinks``: per pair the minima of ``F`` at kinks
        of ``B`` (ascending, ``-1`` for none; :meth:`_kink_minima`).

        ``F`` (``B`` exact, ``R`` interpolated, :class:`ChordGrid`) is scanned at
        :data:`EXTREMUM_SCAN` points per grid cell and at the kinks, in order; an extremum
        counts once ``F`` has moved away from it by :data:`SNAP_PROMINENCE` (hysteresis: a flat
        extremum counts as well as a sharp one, the chord grid's wiggles do not), and
        :data:`KINK_GOLDEN` golden-section steps between the scan points around it place it.
        The moved samples of the full layout (:meth:`_snapped_positions`) take an extremum only
        where it differs from a neighbouring scan point by the prominence: a flat maximum
        between two minima went unseen there and was covered by the band's other samples, which
        an isolated band does not have (labels off by 0.009 on the integrator benchmark's 6-box
        scene). Without the kinks among the scan points, a maximum 8 cm past a kink minimum
        went unseen between the scan points on either side (12 boxes, 16k rays: one ray's label
        off by 0.0087).
        """
        n_ext = self.cfg.isolated_extrema
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

    def _gap_peaks(self, slot_views, slot_ts, count) -> list[GapPeak]:
        """Per slot ``b`` (slots sorted by deepest point): the maximum of the scene SDF (the min
        over the ray's boxes) between the deepest points of slots ``b`` and ``b + 1``
        (detached golden-section search), whether that gap exists, the slots ``a <= b < a'``
        whose boxes cross there and the envelope weight ``lambda_a`` of the first. There the
        scene SDF stops rising and starts falling into the next box; the bands' own samples need
        not hit it, and the descent's opacity telescopes from it.

        Between consecutive deepest points every box of an earlier slot rises and every box of a
        later one falls (each is convex along the ray), so the scene SDF is unimodal there, and
        its maximum is where the least rising box meets the least falling one (with boxes side
        by side, not necessarily the two slots' own boxes). The search takes those least boxes
        over the ``GAP_WINDOW`` slots on each side of the gap, so its cost does not grow with
        the square of the boxes a ray meets. Measured against the search over all of them: 12
        boxes at s = 3 and 10 the same labels; at s = 1 (bands 8 m wide) max error 0.0062
        instead of 0.0017 (a window of 2: 0.0181); 20 boxes, 1k rays, a step takes 8 % longer
        than with a window of 2, the full search 44 %. At that crossing ``B_a = B_a'``
        (``a`` rising with slope ``g_a > 0`` along the ray, ``a'`` falling, ``g_a' < 0``) the
        maximum's derivative is ``lambda_a dB_a + (1 - lambda_a) dB_a'`` with
        ``lambda_a = -g_a' / (g_a - g_a')`` (Danskin, as at a box's ridge); ``-1`` where the
        peak is not such a crossing. Slot indices are returned as Floats (exact small integers)."""
        n_slots = len(slot_views)
        big = 1e30
        none = GapPeak(mi.Float(0.0), mi.Bool(False), mi.Float(-1.0), mi.Float(0.0), mi.Float(0.0), mi.Float(big))
        if n_slots < 2:
            return [none] * n_slots

        def least(t, slots) -> tuple[mi.Float, mi.UInt32]:
            """Least box SDF at ``t`` over the ray's valid ``slots``, and its slot."""
            f, arg = mi.Float(big), mi.UInt32(slots[0])
            for j in slots:
                ol, dl, half = slot_views[j]
                fj = dr.select(count > j, box_sdf_local(ol + t * dl, half), big)
                arg = dr.select(fj < f, j, arg)
                f = dr.minimum(f, fj)
            return f, arg

        def rising(b):
            return range(max(b + 1 - GAP_WINDOW, 0), b + 1)

        def falling(b):
            return range(b + 1, min(b + 1 + GAP_WINDOW, n_slots))

        def neg_scene(b):
            return lambda t: -dr.minimum(least(t, rising(b))[0], least(t, falling(b))[0])

        brackets = [(slot_ts[b], dr.maximum(slot_ts[b + 1], slot_ts[b])) for b in range(n_slots - 1)]
        tps = golden_section([neg_scene(b) for b in range(n_slots - 1)], brackets,
                             self.cfg.golden_iterations, "vsrd_gap_peaks")
        out = []
        for b, tp in enumerate(tps):
            ok = (count > b + 1) & (slot_ts[b] < slot_ts[b + 1])
            (fa, a), (fa2, a2) = least(tp, rising(b)), least(tp, falling(b))
            ga, gb = mi.Float(0.0), mi.Float(0.0)
            for j in [*rising(b), *falling(b)]:
                ol, dl, half = slot_views[j]
                g = dr.dot(box_normal_local(ol + tp * dl, half), dl)
                ga, gb = dr.select(a == j, g, ga), dr.select(a2 == j, g, gb)
            crossing = (ga > 0.0) & (gb < 0.0)
            lam = dr.select(crossing, envelope_weight(dr.select(crossing, ga, 1.0), dr.select(crossing, gb, -1.0)), -1.0)
            out.append(GapPeak(tp, ok, lam, mi.Float(a), mi.Float(a2), dr.minimum(fa, fa2)))
        return out + [none]

    @staticmethod
    def _residual_peaks(sdf, peaks: list[GapPeak], slot_ts: list[mi.Float], reach) -> list[GapPeak]:
        """The gap peaks of :meth:`_gap_peaks` (found on the boxes' ``B``) moved to where the
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

    def _slot_view(self, views, kb: mi.UInt32) -> tuple:
        """Per ray the box-local ``(origin, direction, half)`` of instance ``kb`` (``views`` per
        instance; instance 0 where ``kb`` is no instance)."""
        out = list(views[0])
        for k in range(1, self.field.n):
            out = [dr.select(kb == k, v, o) for v, o in zip(views[k], out)]
        return tuple(out)

    def _snaps(self) -> bool:
        """Whether band and tail samples move to the extrema of ``B + R``
        (:meth:`_snapped_positions`): the tail samples are on and ``residual_tail_scan > 0``."""
        return self._tail_samples()[1] > 0 and self.cfg.residual_tail_scan > 0

    def _snapped_slots(self, sdf, slots: list[Slot], minima: list[tuple]) -> list[list[list[mi.Float]]]:
        """Moved positions of every slot's samples in the order :meth:`_sub_bands` reads them: the first
        tail's ``kp`` in ``(hi, extra)``, the second tail's ``kq`` in ``(extra, tail end]``, the
        band's first half's ``K/2 - 1`` in ``(lo, mid)`` (its last sample, the centre, stays)
        and its second half's ``K/2 - 1`` in ``(mid, hi)`` (its last sample stays too: where a
        hit band ends at its least ``B + R``, that is ``hi``, and a maximum just before it took
        the sample when it could move: trained fields, labels off by 0.05); per part a list (slot) of lists
        (sample) of arrays (ray). ``minima``: the minima of each (slot, ray) pair's ``F`` at
        the kinks and bends of its ``B`` (:meth:`_kink_minima`)."""
        kp, kq = self._tail_samples()
        k1, k2 = self._halves(self.cfg.band_samples)
        lo, mid, hi, extra, tail = ([getattr(sl, name) for sl in slots]
                                    for name in ("lo", "mid", "hi", "extra", "tail_end"))
        empty = [[] for _ in slots]
        return [self._snapped_positions(sdf, hi, extra, kp + 1, kp, kinks=minima) if kp else empty,
                self._snapped_positions(sdf, extra, tail, kq, kq, kinks=minima),
                self._snapped_positions(sdf, lo, mid, k1, k1 - 1, True, kinks=minima) if k1 > 1 else empty,
                self._snapped_positions(sdf, mid, hi, k2, k2 - 1, kinks=minima) if k2 > 1 else empty]

    @staticmethod
    def _kink_minima(sdf, kinks: list[mi.Float], bends: tuple[list[mi.Float], list[mi.Float]] = ([], []),
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

    @staticmethod
    def _pair_views(slot_views) -> tuple:
        """The box-local ray origins, directions and half sizes of every (slot, ray) pair,
        slot-major."""
        return tuple(concat([sv[i] for sv in slot_views]) for i in range(3))

    def _pair_sdf(self, slot_views, slot_inst) -> Callable[[mi.UInt32, mi.Float], mi.Float]:
        """``at(pair, t)``: the instance SDF ``F = B + R`` of (slot, ray) pairs ``pair`` at ray
        parameters ``t`` (for :class:`PairScan`), detached and exact (``residual_grid = 0``;
        :class:`ChordGrid` interpolates ``R`` instead); invalid slots get their box's ``B``
        only."""
        flat = self._pair_views(slot_views)
        inst = concat(slot_inst)

        def at(pair: mi.UInt32, t: mi.Float) -> mi.Float:
            ol, dl, half = [dr.gather(type(x), x, pair) for x in flat]
            return box_sdf_local(ol + t * dl, half) + self._pair_residuals(flat, inst, pair, t)

        return at

    def _residual_omega(self) -> float:
        """The residual encoding's highest frequency in rad/m: ``2^(F-1) pi`` times its input
        scale (4 rad/m by default)."""
        rcfg = self.field.residual.cfg
        return math.pi * 2.0 ** (rcfg.frequencies - 1) * rcfg.input_scale

    def _chord_grid(self, dec, slot_views, slot_inst, count, picked: list[Picked]) -> "ChordGrid":
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
        spacing = self.cfg.residual_grid / self._residual_omega()
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
        flat, inst = self._pair_views(slot_views), concat(slot_inst)
        lattice = self._residual_lattice(dec, total)
        if lattice is None:
            r = self._pair_residuals(flat, inst, pair, t_grid)
        else:
            pl, ik = self._pair_points(flat, inst, pair, t_grid)
            r = lattice.residual(ik, pl)
        dr.eval(r)
        return ChordGrid(flat, a, inv_h, points, first, r, n, busy, rank)

    def _residual_lattice(self, dec, grid_points: int) -> ResidualLattice | None:
        """The residual tabulated per instance (:class:`~vsrd_plugins.sdf.ResidualLattice`,
        spacing ``residual_lattice / omega``, over each box enlarged by the residual's reach)
        when that costs fewer MLP evaluations than ``grid_points`` chord-grid points do
        (counting a lookup as :data:`~vsrd_plugins.sdf.LATTICE_LOOKUP_COST` of one), else
        ``None``. A dense ray batch crosses each box many times and pays for the table once
        (6 boxes, 16k rays: 0.41M nodes instead of 1.24M grid points, chord grid 0.10 -> 0.06 s;
        12 boxes 0.16 -> 0.10 s); a sparse one is cheaper along its chords (at 4k rays and
        below on the integrator benchmark)."""
        if self.cfg.residual_lattice <= 0:
            return None
        spacing = self.cfg.residual_lattice / self._residual_omega()
        margin, half = dr.detach(self._residual_reach()), [dr.detach(h) for h in dec.half]
        dr.eval(margin, half)  # one kernel, then plain reads
        extents = np.stack([h.numpy() for h in half], axis=1) + float(margin[0])
        nodes = int(ResidualLattice.node_counts(extents, spacing).prod(axis=1).sum())
        if nodes >= grid_points * (1.0 - LATTICE_LOOKUP_COST):
            return None
        return self.field.residual.lattice(self.field.residual_weights(), extents, spacing)

    @staticmethod
    def _pair_points(flat, inst: mi.UInt32, pair: mi.UInt32, t: mi.Float) -> tuple[mi.Vector3f, mi.UInt32]:
        """Box-local point at ray parameter ``t`` and instance of each lane's (slot, ray)
        ``pair`` (``flat``, ``inst``: as for :meth:`_pair_residuals`)."""
        ol, dl = [dr.gather(type(x), x, pair) for x in flat[:2]]
        return ol + t * dl, dr.gather(mi.UInt32, inst, pair)

    def _pair_residuals(self, flat, inst: mi.UInt32, pair: mi.UInt32, t: mi.Float) -> mi.Float:
        """Residual ``R`` of each lane's (slot, ray) ``pair`` at ray parameter ``t`` (detached;
        ``flat``: the pairs' box-local origins, directions and half sizes; ``inst``: the pairs'
        instances, ``num_instances`` for an invalid slot, whose ``R`` is 0), every instance in
        one batched evaluation."""
        pl, ik = self._pair_points(flat, inst, pair, t)
        dr.eval(pl, ik)
        groups = [(k, dr.compress(ik == k)) for k in range(self.field.n)]
        groups = [(k, idx) for k, idx in groups if dr.width(idx)]
        res = self.field.residual.evaluate_grouped(self.field.residual_weights(), [k for k, _ in groups],
                                                   [dr.gather(mi.Vector3f, pl, idx) for _, idx in groups])
        out = dr.zeros(mi.Float, dr.width(t))
        for (_, idx), rk in zip(groups, res):
            dr.scatter(out, rk, idx)
            dr.eval(out)  # one kernel per instance: pending scatters of equal width share one
        return out

    def _snapped_positions(self, sdf, starts: list[mi.Float], ends: list[mi.Float], k_sub: int, k: int,
                           dense_at_b: bool = False,
                           kinks: list[tuple[mi.Float, ...]] = ()) -> list[list[mi.Float]]:
        """Per slot the positions of the first ``k`` samples of the sub-band ``(starts[b],
        ends[b]]`` of ``k_sub`` samples (:meth:`_sub_sample`), moved to the local extrema of
        ``F = B + R`` (detached; ``sdf``: the :class:`PairScan` of the pairs).

        Along a ray that runs close to a face, ``B + R`` has several shallow local minima and
        maxima, and the discrete opacity telescopes over each monotone run: it is right where
        the samples sit on those extrema, whatever lies between. Uniform samples straddle them
        (integrator benchmark's 12-box residual scene: labels max 0.0227 with 12 tail samples,
        0.0117 with 32; moved, 3 scan points per sample: 0.0055 with 12). Sample ``i``
        owns the cell between its nominal position and its predecessor's
        (:meth:`_sub_sample`); ``residual_tail_scan`` points per cell (the last at the nominal
        position) are scanned, over the cells of the ``k`` moved samples and, where ``k <
        k_sub``, the fixed next sample's. Every scan point that is a local extremum of the scan
        (by more than :data:`SNAP_PROMINENCE`) places a sample between its two neighbours
        (:meth:`_refined_extrema`: golden-section steps; the vertex of the parabola through
        the three missed the extrema of trained residual fields by up to 0.14 m); ``kinks`` (per pair, ascending, with ``F`` there,
        :meth:`_kink_minima`), the minima of ``F`` at kinks and sharp bends of ``B``, place one
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
        :meth:`_adaptive_groups` holds). Random 2-3-box scenes (256 rays, seeds 40-299): scenes
        with a label above 0.01 19 -> 9 of 260, worst 0.039 -> 0.019, against one sample per
        cell that took its cell's largest extremum and lent its runner-up to a free neighbour
        (which left a cell with two extrema, a cell holding the deepest point, or extrema
        crowding one end of a sub-band with one sample short); with the kinks, bends and
        residual peaks none of the 260 (README, "Kinks, bends and peaks").
        """
        per = self.cfg.residual_tail_scan
        n_slots, n = len(starts), dr.width(starts[0])
        a, b = concat(starts), concat(ends)
        # the cells of the k moved samples, and the fixed next sample's (k < k_sub): an extremum
        # there takes the last moved sample where it is free
        cells = k + 1 if k < k_sub else k
        nominal = [self._sub_sample(a, b, i, k_sub, dense_at_b) for i in range(cells + 1)]

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
        flat = scan_point(self._sub_sample(ap, bp, dr.select(cell > 0, cell - 1, 0), k_sub, dense_at_b),
                          self._sub_sample(ap, bp, cell, k_sub, dense_at_b), j)
        values = sdf(flat, len(ts))
        v = [sdf.spread(values, i) for i in range(len(ts))]
        # the local extrema of the scan and the kinks of B where F has a local minimum (see
        # _kink_minima; exact, where a search between the scan points on either side would miss them), in
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
                # placed between x0 and x2 once taken (_refined_extrema)
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
        pos = self._refined_extrema(sdf, pos, brackets)
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

    @staticmethod
    def _refined_extrema(sdf, pos: list[mi.Float], brackets: list[tuple]) -> list[mi.Float]:
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

    def _residual_minima(self, sdf, slot_views, count, picked: list[Picked]) -> list[mi.Float]:
        """Per slot, where the instance SDF ``F = B + R`` is least along the ray (detached;
        ``sdf``: the :class:`PairScan` of the pairs).

        ``R >= 0`` moves ``F``'s minimum off the box's: along a ray grazing a face ``B`` is
        nearly flat and ``R`` decides, and inside a box ``F`` can keep falling past ``B``'s
        deepest point. The telescoping integral needs that minimum as a sample (labels were off
        by p99 0.025 with the box's, 6 boxes at s = 10). ``F`` is not convex, so the search
        scans ``residual_scan`` points of a window (the chord ``[entry, exit]`` of a box the
        ray enters, ``[t* - w, t* + w]`` around the box's closest approach otherwise), keeps the
        least of them and the box's own minimum ``t*``, and refines it by ``residual_golden``
        golden-section steps between its neighbours. One batched residual evaluation per step
        (every slot and instance together), outside the AD graph.
        """
        cfg = self.cfg
        n_slots, n = len(slot_views), dr.width(count)
        w = self._reach()
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
        if cfg.residual_golden > 0:  # refine between the best candidate's neighbours
            lo = dr.maximum(t_min - step, a)
            hi = dr.minimum(t_min + step, b)
            x1, x2 = golden_probes(lo, hi)
            state = (lo, hi, x1, x2, sdf.full(x1), sdf.full(x2))
            # unrolled, not golden_section's symbolic loop: the residual MLP runs as tensor-mode
            # kernels, which cannot be traced inside one
            for _ in range(cfg.residual_golden):
                state = golden_step(state, sdf.full)
                dr.eval(state)
            f_min = dr.minimum(state[4], state[5])
            t_min = dr.select(f_min < best_v, golden_argmin(state), t_min)
        return [block_of(t_min, b_, n) for b_ in range(n_slots)]

    @staticmethod
    def _halves(kk: int) -> tuple[int, int]:
        """Band samples up to a band's centre (the last of them at it) and after it."""
        k1 = max(kk // 2, 1)
        return k1, kk - k1

    def _tail_samples(self) -> tuple[int, int]:
        """Tail samples per band before and after its minimum sample (``residual_tail`` split in
        two while the residual field is on, else none). With the field, ``B + R`` along a ray
        that runs close to a face can have several local minima, each a descent whose opacity
        telescopes separately; the band's own samples cover a reach on either side of the
        least one only. The first tail fills a hit band from a reach past the surface entry to
        the minimum, the second from the band's end to the enlarged box's exit. A band that
        already ends at its minimum (a miss; a hit whose minimum is within a reach of its
        entry) has no stretch for the first tail: its extra sample then sits halfway from the
        band's end to the exit and the two tails share that stretch (they stacked on one point
        before: 32 random 2-3-box scenes, labels mean max 0.0090 -> 0.0075, mean p99 0.0053 ->
        0.0044, same sample count).
        """
        kt = self.cfg.residual_tail if self._residual_search() else 0
        return kt // 2, kt - kt // 2

    def _residual_search(self) -> bool:
        """Whether bands are placed at the least ``B + R`` (:meth:`_residual_minima`): the
        residual field is on and ``residual_scan > 0``. The tail samples come with it."""
        return self.field.residual_reach > 0 and self.cfg.residual_scan > 0

    @staticmethod
    def _sub_sample(a, b, i, k: int, dense_at_b: bool = False):
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

    def _count_before(self, a, b, k: int, before, dense_at_b: bool = False, n: int | None = None):
        """Number of samples ``i = 1..n`` (default ``k``) of the ``k`` of sub-band ``(a, b]`` for
        which ``before`` holds (it holds for a prefix of them: the samples are sorted). A binary
        search on the samples themselves: inverting the sample formula misplaced ranks by more
        than one where a band is narrow next to its distance (float rounding), which left rays
        unsorted."""
        return count_prefix(k if n is None else n, lambda i: self._sub_sample(a, b, i, k, dense_at_b), before)

    def _sub_bands(self, sl: Slot, kk: int, kp: int, kq: int, snapped: bool, extrema: bool = False) -> list[tuple]:
        """A band's runs of samples between its entry and its extra sample and after it (see
        :meth:`_adaptive_groups`), as ``(first index in the band, count, value(i), counter(before))``:
        ``value`` gives the ``i``-th (1-based) sample, ``counter`` how many of them satisfy
        ``before`` (a prefix). From :meth:`_sub_sample`'s formula, or from the positions
        :meth:`_snapped_slots` moved (``snapped``; :attr:`Slot.moved`), or, for an isolated
        ray with the residual field (``extrema``), one run of every sample after the entry
        (:attr:`Slot.isolated`)."""
        lo, mid, hi, ex = sl.lo, sl.mid, sl.hi, sl.extra
        k1, k2 = self._halves(kk)
        out = []

        def formula(first, k_run, a, b, k_sub, dense_at_b=False):
            out.append((first, k_run, lambda i: self._sub_sample(a, b, i, k_sub, dense_at_b),
                        lambda before: self._count_before(a, b, k_sub, before, dense_at_b, n=k_run)))

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

    def _adaptive_groups(self, dec, o, d, time, bands: tuple | None = None) -> Iterator[SampleGroup]:
        """Sample positions for the adaptive strategy, one group per band count and layout
        (isolated rays, :meth:`_isolated`, get ``isolated_band_samples`` instead of ``K``).

        Yields a :class:`SampleGroup` ``(rays, t, m, active, inst, deepest, peak, own)``: rays with exactly ``g`` bands get
        ``m = g (K + 3 + T)`` samples (entry, ``K`` band samples, the first tail, closest approach /
        exit, the second tail, and the scene SDF's peak before the next band, per band; ``T`` tail
        samples only with the residual search, :meth:`_tail_samples`), merged in order by rank: a
        sample's index in its band plus, per other band, how many of that band's samples come
        before it (a binary search: bands are internally sorted), so no per-ray sort is needed.
        ``active`` masks the padding copy of a single-ray group; ``inst`` holds the ``g`` band instances of
        each ray (the only instances evaluated at its samples); ``deepest`` is, per sample, the band
        whose box's deepest point along the ray this sample is (``g`` for none); ``peak`` per sample
        the two bands whose boxes cross there and the envelope weight of the first if it is a gap
        peak (else ``-1``); ``own`` per sample its band in an isolated group (``None`` otherwise).
        """
        kp, kq = self._tail_samples()
        if bands is None:
            bands = self._adaptive_bands(dec, o, d, time)
        ray_idx, count, slots, slot_inst, slot_hit, isolated, _ = bands
        if not slots:
            return
        # samples moved to the extrema of B + R (:meth:`_snapped_slots`) are data, not
        # formulas: :attr:`Slot.moved` holds them (the full-band layout only)
        moved = self._snaps()
        # (isolated rays?, K): rays of isolated bands get their own groups with fewer samples
        layouts = [(False, self.cfg.band_samples)]
        if self._isolates():
            layouts.append((True, self.cfg.isolated_band_samples))
        for g, (iso, kk) in ((g, lay) for g in range(1, len(slots) + 1) for lay in layouts):
            # with the residual field an isolated band is its entry, the samples of
            # Slot.isolated and the gap peak (the extra sample among them)
            extrema = iso and moved
            j_ex, per = self._band_layout(extrema, kk)
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
                k1, k2 = self._halves(kk)
                # this lane's own sample value: entry, K/2 samples in (lo, mid], K/2 in (mid, hi],
                # the first tail in (hi, extra), extra, the second tail in (extra, tail end], and
                # the gap peak after the band (its own one-sample group in the merge)
                is_peak = j == per - 1
                # per band its sub-bands: (first index, samples, values) with values a formula of
                # the 1-based index or the moved positions (see _snapped_slots)
                snap = moved and not iso
                parts = [self._sub_bands(sl[b], kk, kp, kq, snap, extrema) for b in range(g)]
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
            yield SampleGroup(rays, ts, m, active, inst, deepest, (peak_a, peak_b, peak_lam), own, sub, kink_lam, real)
