"""The ``vsrd_silhouette`` integrator: accuracy, gradients, robustness, Mitsuba plumbing, fitting.

Accuracy reference: the integrator's own differentiable integral (``integrate_at``) evaluated on a
uniform grid of samples fine enough to resolve ``1/s`` (``REF_SPACING_S``), which converges to the
continuous NeuS integral. The paper-count dense sampling (100 + 100) is itself up to ~0.4 off that
reference at s = 10 on grazing rays (its 1 m coarse spacing misses thin dips), so adaptive is
compared with the accurate reference (and with a dense run of 2000 + 400 samples), not with it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins.common import golden_minimum, illinois_root
from vsrd_plugins.silhouette import VSRDSilhouetteIntegrator
from vsrd_plugins.silhouette import bands as bands_module
from vsrd_plugins.silhouette import residual_search
from vsrd_plugins.silhouette.bands import adaptive_bands
from vsrd_plugins.silhouette.dense import dense_positions
from vsrd_plugins.silhouette.extrema import snapped_positions, snapped_slots
from vsrd_plugins.silhouette.integral import GAUSS_QUANTILES, accrual_quantiles
from vsrd_plugins.silhouette.layout import adaptive_groups, sub_bands
from vsrd_plugins.silhouette.residual_search import (ChordGrid, PairScan, kink_minima, residual_lattice,
                                                     residual_peaks)
from vsrd_plugins.silhouette.settings import halves
from vsrd_plugins.silhouette.slots import KINK_MINIMA, GapPeak, Slot, sub_sample
from vsrd_mi.bench.measure import central_differences, fd_steps, new_kernels, reference_labels
from vsrd_mi.bench.scenes import (BOX_KEYS, BenchConfig, random_scene, silhouette_integrator,
                                  training_rays)
from vsrd_plugins import box_properties

#: accurate dense sample counts (coarse, fine)
DENSE_ACCURATE = (2000, 400)
#: gradient cosine asserted in the slow full accuracy run (see the module docstring of the report)
GRAD_COSINE_MIN = 0.99
#: label error bounds of the slow full accuracy run (the default K = 16 at every s). Measured:
#: max 0.0002-0.0087 and p99 0.0002-0.0034 (one label point per interval: max 0.0114 at 12 boxes,
#: s = 3; the two-point labels brought it within the issue's max <= 0.01).
FULL_MAX_ABS = 0.01  # the issue's bound (latest run: max 0.0087, 12 boxes at s = 3)
FULL_P99_ABS = 0.005  # latest run: p99 at most 0.0034
#: rays of the slow test's central differences of the converged integral
FD_RAYS = 256
#: scan points per moved sample (the default ``residual_tail_scan``)
SCAN = 3
#: AD vs central differences (float32 labels; see test_gradients_match_finite_differences)
FD_TOLERANCE = 0.25
FD_COSINE_MIN = 0.98


# ----------------------------------------------------------------------------------------------
# scene and ray helpers
# ----------------------------------------------------------------------------------------------


def make(scene: dict, **kw) -> VSRDSilhouetteIntegrator:
    """An integrator of ``scene`` with plugin properties and settings ``kw``."""
    return silhouette_integrator(scene, **kw)


def to_mi(o, d, t):
    return (mi.Point3f(np.ascontiguousarray(o.T, np.float32)),
            mi.Vector3f(np.ascontiguousarray(d.T, np.float32)), mi.Float(t.astype(np.float32)))


def labels_and_grads(it, fn, weights):
    """Soft labels (instances x rays) and the gradient of ``sum weights * labels`` (all box params)."""
    for k in BOX_KEYS:
        dr.enable_grad(it.field.params[k])
    labels = fn(it)[:it.field.n]
    loss = labels[0] * weights[0]
    for lab, w in zip(labels[1:], weights[1:]):
        loss = loss + lab * w
    dr.backward(dr.sum(loss))
    vals = np.stack([np.array(dr.detach(x)) for x in labels])
    grad = np.concatenate([np.array(dr.grad(it.field.params[k])) for k in BOX_KEYS])
    for k in BOX_KEYS:
        it.field.params[k] = dr.detach(it.field.params[k])
    return vals, grad


def cosine(a, b) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


# ----------------------------------------------------------------------------------------------
# accuracy of adaptive sampling
# ----------------------------------------------------------------------------------------------


def accuracy_case(n_inst: int, s: float, n_rays: int, seed: int, with_grads: bool):
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n_inst, dynamic=True)
    rays = to_mi(*training_rays(rng, scene, n_rays, max_time=2.0))
    weights = [mi.Float(rng.normal(size=n_rays).astype(np.float32)) for _ in range(n_inst)]
    kw = {"sharpness": s, "temperature": 1.0 / s}
    render = lambda it: it.render_rays(*rays)  # noqa: E731
    out = {}
    ref_it = make(scene, sampling="dense", **kw)
    cases = [("ref", ref_it, lambda it: reference_labels(it, scene, rays, s)),
             ("adaptive", make(scene, **kw), render)]
    if with_grads:
        cases.append(("dense", make(scene, sampling="dense", coarse_samples=DENSE_ACCURATE[0],
                                    fine_samples=DENSE_ACCURATE[1], **kw), render))
    for name, it, fn in cases:
        if with_grads:
            out[name] = labels_and_grads(it, fn, weights)
        else:
            with dr.suspend_grad():
                out[name] = (np.stack([np.array(x) for x in fn(it)[:n_inst]]), None)
    return out


def np_accrual_quantile(s: float, fa: float, fb: float, q: float, n: int = 200_000) -> float:
    """Where an interval with ``f`` linear from ``fa`` to ``fb`` has accrued the fraction ``q`` of
    its NeuS opacity, by brute force: the discrete NeuS opacity of ``n`` sub-intervals
    (float64), accumulated and interpolated (independent of the closed form)."""
    f = np.linspace(fa, fb, n + 1)
    phi = 1.0 / (1.0 + np.exp(-s * f))
    trans = phi / phi[0]  # transmittance after each sub-interval (telescoped, descending f)
    acc = 1.0 - trans
    return float(np.interp(q * acc[-1], acc, np.linspace(0.0, 1.0, n + 1)))


@pytest.mark.parametrize("s, fa, fb", [(10.0, 0.3, -0.2), (3.0, 1.0, 0.2), (1.0, 0.5, -2.0),
                                        (100.0, 0.05, -0.05), (10.0, -0.5, -0.9), (1000.0, 0.2, -0.1)])
def test_accrual_quantiles_match_brute_force(s, fa, fb):
    """The two label positions of an interval are where it has accrued the Gauss-Legendre
    fractions of its opacity; in the sharp limit both sit at the surface crossing."""
    log1ma = mi.Float(float(np.logaddexp(0.0, -s * fa) - np.logaddexp(0.0, -s * fb)))  # log(1 - alpha)
    thetas = accrual_quantiles(mi.Float(s), mi.Float(fa), mi.Float(fb), log1ma)
    for q, theta in zip(GAUSS_QUANTILES, thetas):
        expected = np_accrual_quantile(s, fa, fb, q)
        assert abs(float(theta[0]) - expected) < 2e-3, (q, float(theta[0]), expected)
    if s >= 1000.0:
        crossing = fa / (fa - fb)
        assert all(abs(float(t[0]) - crossing) < 0.02 for t in thetas)


def test_accrual_quantiles_of_flat_or_rising_intervals_are_uniform():
    """No opacity (``f`` rising) or a flat ``f``: the quantiles of a uniform weight."""
    fa, fb = mi.Float([0.1, 0.3]), mi.Float([0.4, 0.3])
    thetas = accrual_quantiles(mi.Float(10.0), fa, fb, mi.Float([0.0, 0.0]))
    for q, theta in zip(GAUSS_QUANTILES, thetas):
        np.testing.assert_allclose(np.array(theta), [q, q], atol=1e-7)


# default: small cases (a cold 6-instance adaptive compile alone takes ~90 s on 2 cores);
# 6 and 12 instances run in the slow full test.
@pytest.mark.parametrize("n_inst,s", [(1, 10.0), (3, 3.0), (2, 10.0)])
def test_adaptive_matches_reference(n_inst, s):
    out = accuracy_case(n_inst, s, 128, seed=10 + n_inst, with_grads=False)
    err = np.abs(out["adaptive"][0] - out["ref"][0]).max(0)
    assert np.all(np.isfinite(err))
    # enough of the rays see something, so the comparison is not vacuous
    assert (out["ref"][0].sum(0) > 0.5).mean() > 0.3
    print(f"n={n_inst} s={s} max={err.max():.4f} p99={np.quantile(err, 0.99):.4f}")
    assert err.max() <= 0.05, err.max()
    assert np.quantile(err, 0.99) <= 0.01, np.quantile(err, 0.99)


def residual_label_error(seed: int, n_inst: int, variants: dict, quantile: float = 0.99) -> dict:
    """``quantile`` (default the 99th percentile; 1: the max) over 256 training rays (s = 10,
    residual field on) of each ray's largest label error against the reference, per
    ``variants`` entry (integrator options)."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n_inst)
    rays = to_mi(*training_rays(rng, scene, 256))
    kw = dict(sharpness=10.0, temperature=0.1, residual=True)
    with dr.suspend_grad():
        ref = np.stack([np.array(x) for x in
                        reference_labels(make(scene, sampling="dense", **kw), scene, rays, 10.0)[:n_inst]])
        err = {}
        for name, opts in variants.items():
            labels = make(scene, **opts, **kw).render_rays(*rays)[:n_inst]
            ray_err = np.abs(np.stack([np.array(x) for x in labels]) - ref).max(axis=0)
            err[name] = float(np.quantile(ray_err, quantile))
    print(err)
    return err


def test_adaptive_with_residual_samples_the_field_minimum():
    """With the residual field a ray's band ends at the least ``B + R`` along the ray (searched),
    not at the box's least ``B``: on rays that graze a box, ``R`` moves the minimum (one box,
    s = 10; measured p99 0.0019 with the scan, 0.0068 with the box's minimum; 0.0038 with the
    scan and golden-section steps before the tail samples)."""
    p99 = residual_label_error(21, 1, {4: {"residual_scan": 4}, 0: {"residual_scan": 0}})
    assert p99[4] <= 0.005 and p99[4] < p99[0]


@pytest.mark.parametrize("seed, n_inst", [(21, 2), (24, 3)])
def test_adaptive_with_residual_samples_the_tails(seed, n_inst):
    """With the residual field ``B + R`` along a ray near a face can dip more than once; each
    descent's opacity telescopes separately. Tail samples (``residual_tail``) between a reach past
    the entry and the minimum, and from the band's end to the enlarged box's exit, catch the
    others (s = 10; measured p99 0.0023 / 0.0052 with the default 12, 0.0054 / 0.0098 without;
    0.0025 / 0.0051 before a miss's tails were split around its extra sample)."""
    p99 = residual_label_error(seed, n_inst, {None: {}, 0: {"residual_tail": 0}})
    assert p99[None] <= 0.006 and p99[None] < 0.6 * p99[0]


@pytest.mark.parametrize("seed", [28, 33])
def test_adaptive_with_residual_samples_the_extrema(seed):
    """The opacity telescopes over each monotone run of ``B + R``; along a ray near a face the
    field has several shallow minima and maxima, which band and tail samples at their nominal
    places straddle. Moved to the extrema a detached scan finds in their cells
    (``residual_tail_scan``), the worst ray's label error falls (3 boxes, s = 10; measured max
    0.0152 -> 0.0046 and 0.0207 -> 0.0037)."""
    err = residual_label_error(seed, 3, {None: {}, 0: {"residual_tail_scan": 0}}, quantile=1.0)
    assert err[None] <= 0.006 and err[None] < 0.5 * err[0]


@pytest.mark.parametrize("seed, n_inst", [(22, 3), (33, 2)])
def test_lengthwise_miss_spreads_its_band_over_the_chord(seed, n_inst):
    """A ray grazing a box lengthwise that leaves the enlarged box soon after its least
    ``B + R`` had ``K/2`` wide cells before that minimum (two extrema of ``B + R`` in one cell,
    one movable sample) and its tails stacked on the chord's end; with the minimum at the extra
    sample and the band spread evenly before it (``_lengthwise_miss``) the worst ray's label
    error falls below the bound (3 and 2 boxes, s = 10; measured 0.0135 -> 0.0071 and
    0.0134 -> 0.0081)."""
    err = residual_label_error(seed, n_inst, {None: {}}, quantile=1.0)
    assert err[None] <= 0.01


@pytest.mark.parametrize("residual", [False, True])
def test_band_search_returns_evaluated_arrays(residual):
    """:func:`adaptive_bands` evaluates every per-ray array it returns in one go: the sample
    layout gathers from them per band count, and a gather from an unevaluated array launches a
    kernel of its own (``dr.eval`` does not look inside named tuples: while ``Slot`` was one,
    passing the slots as they were cost 18 more kernels per 1000-ray step, 115 with the residual
    field, and a 16k-ray step 0.05 -> 0.11 s)."""
    rng = np.random.default_rng(3)
    scene = random_scene(rng, 3)
    o, d, t = training_rays(rng, scene, 64)
    it = make(scene, residual=residual)
    with dr.suspend_grad():
        bands = adaptive_bands(it.context(), it.field.decode(), *to_mi(o, d, t))
    count, slots, slot_inst, slot_hit, isolated, grid = (bands.count, bands.slots, bands.inst, bands.hit,
                                                         bands.isolated, bands.grid)
    assert slots and (len(slots[0].moved) > 0) == residual and (grid is not None) == residual
    arrays = [count, isolated, *slot_inst, *slot_hit] + [x for sl in slots for x in sl.arrays()]
    if grid is not None:
        arrays += [*grid.views[0], *grid.views[1], *grid.views[2], grid.start, grid.inv_step, grid.points,
                   grid.first, grid.r]
    assert all(x.state in (dr.VarState.Evaluated, dr.VarState.Literal) for x in arrays), \
        [str(x.state) for x in arrays]


def test_residual_tail_samples_do_not_pile_up():
    """With the residual field a band that already ends at its minimum (every miss, and a hit
    whose least ``B + R`` is within a reach of its entry) splits the rest of the chord between
    its two tails instead of stacking the first tail on one point: 7 % of the samples of this
    scene repeat another of their ray's (the gap-peak slot of a ray with no gap copies a sample),
    19 % when the first tail sat on the band's end."""
    rng = np.random.default_rng(7)
    scene = random_scene(rng, 3)
    o, d, t = training_rays(rng, scene, 256)
    it = make(scene, sharpness=10.0, temperature=0.1, residual=True)
    total = repeated = 0
    with dr.suspend_grad():
        ctx = it.context()
        for grp in adaptive_groups(ctx, adaptive_bands(ctx, it.field.decode(), *to_mi(o, d, t))):
            m = grp.m
            samples = np.array(grp.t).reshape(-1, m)
            total += samples.size
            repeated += sum(m - len(np.unique(row)) for row in samples)
    assert repeated / total < 0.1, repeated / total


@pytest.mark.parametrize("residual, s", [(False, 1.0), (True, 1.0), (True, 10.0)])
def test_adaptive_samples_are_merged_in_order(residual, s, monkeypatch):
    """Crowded scene, soft schedule (every ray meets most of 12 boxes) and, with the residual
    field, a sharp one (most rays isolated): each ray's merged band samples (entry, K band
    samples, deepest point / exit and gap peak per band, and with the residual field the two
    tails; an isolated ray's entry, centre, the band's end, extra sample, exit, extrema of
    ``B + R``, kink minima and gap peak) come out sorted (up to ties one float32 ulp apart) with
    no unwritten slot, and the gap peaks lie between bands."""
    rng = np.random.default_rng(112)
    scene = random_scene(rng, 12, dynamic=True)
    o, d, t = training_rays(rng, scene, 512, max_time=2.0)
    it = make(scene, sharpness=s, temperature=1.0 / s, residual=residual,
              isolated_group_cost=0)  # isolated groups at any size
    kk = it.settings.band_samples + (it.settings.residual_tail if residual else 0)
    # isolated rays' groups use the smaller layout
    layouts = {kk + 3, (6 + it.settings.isolated_extrema + KINK_MINIMA) if residual
               else it.settings.isolated_band_samples + 3}
    groups, isolated = 0, 0
    with dr.suspend_grad():
        ctx = it.context()
        for grp in adaptive_groups(ctx, adaptive_bands(ctx, it.field.decode(), *to_mi(o, d, t))):
            g, m = len(grp.inst), grp.m
            assert m % g == 0 and m // g in layouts
            isolated += grp.own is not None
            T = np.array(grp.t, dtype=np.float64).reshape(-1, m)
            steps = np.diff(T, axis=1)
            assert steps.min() >= -1e-6 * max(1.0, np.abs(T).max()), steps.min()
            # an unwritten slot would read 0 after a positive sample
            first = np.argmax(T > 0, axis=1)
            assert not any(np.any(row[f:] == 0) for row, f in zip(T, first))
            groups += 1
    assert groups >= 3  # several band counts were exercised
    assert isolated or s < 10.0  # the sharp schedule exercised the isolated layout


def test_isolated_rays_are_those_whose_boxes_do_not_interact():
    """A ray is isolated when the enlarged boxes it meets are disjoint along it: two boxes 10 m
    apart on one line of sight are, two boxes 0.2 m apart side by side are not (their culling
    margins overlap). With the residual field a ray is isolated only where each of its bands
    has at most ``isolated_extrema`` extrema of ``B + R``: the ray through the boxes' centres
    runs along a flat stretch of ``B`` inside each, where the field's wiggles make 5 and 3.
    Band slots go up to the most boxes a ray meets."""
    # two more boxes far to the side that neither ray meets: no slots for them
    centres = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 20.0], [2.1, 0.0, 20.0], [30.0, 0.0, 20.0],
                        [-30.0, 0.0, 20.0]])
    scene = {"centre": centres, "size": np.array([[1.9, 1.5, 4.0]] * 5), "yaw": np.zeros(5)}
    # one ray through the first two boxes' centres, one grazing between the side-by-side pair
    d = np.array([[0.0, 0.0, 1.0], [1.05 / 20.0, 0.0, 1.0]])
    rays = to_mi(np.zeros((2, 3)), d / np.linalg.norm(d, axis=1, keepdims=True), np.zeros(2))
    for residual, extrema, expected in ((False, 3, [True, False]), (True, 3, [False, False]),
                                        (True, 5, [True, False])):
        it = make(scene, sharpness=10.0, temperature=0.1, residual=residual, isolated_extrema=extrema,
                  isolated_group_cost=0)  # two rays pay for a group here
        with dr.suspend_grad():
            bands = adaptive_bands(it.context(), it.field.decode(), *rays)
        count, slots, isolated = bands.count, bands.slots, bands.isolated
        assert list(np.array(count)) == [2, 3]
        assert len(slots) == 3  # slots up to the most boxes a ray meets, not one per instance
        assert list(np.broadcast_to(np.array(isolated), 2)) == expected


@pytest.mark.parametrize("seed", [0, 1])
def test_isolated_band_samples_keep_labels_and_gradients(seed):
    """Isolated rays' bands with 1 sample instead of K = 16, and only their own instance at
    each sample, give the same labels (measured <= 0.0006 apart) and gradients (cosine 1.0000)
    on 6-box scenes with touching pairs, with 12-36 % fewer samples."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, 6, dynamic=True)
    o, d, t = training_rays(rng, scene, 512, max_time=2.0)
    rays = to_mi(o, d, t)
    weights = [mi.Float(rng.normal(size=512).astype(np.float32)) for _ in range(6)]
    out = {}
    for name, kw in (("isolated", {}), ("full", {"isolated_rays": False})):
        it = make(scene, sharpness=10.0, temperature=0.1, **kw)
        out[name] = labels_and_grads(it, lambda it: it.render_rays(*rays), weights) + (it.last_stats["samples"],)
    assert np.abs(out["isolated"][0] - out["full"][0]).max() <= 2e-3
    assert cosine(out["isolated"][1], out["full"][1]) >= 0.9999
    assert out["isolated"][2] < 0.95 * out["full"][2]


@pytest.mark.parametrize("seed, n_inst", [(28, 3), (33, 3), (41, 6)])
def test_isolated_residual_rays_keep_labels_and_gradients(seed, n_inst):
    """With the residual field an isolated ray whose bands have few extrema of ``B + R`` gets
    only its entry, anchors, extrema and kink minima per band (11 samples instead of 31): the
    labels stay within the bound of the reference and within 2e-3 of the full layout's, the
    gradient at cosine >= 0.999 of it, with fewer samples (s = 10; measured: max vs reference
    equal to the full layout's, labels <= 1e-3 apart, cosine >= 0.99999, 77-91 % of the
    samples on these crowded scenes, 44 % on the integrator benchmark's 6 boxes / 16k rays)."""
    variants = {"isolated": {"isolated_group_cost": 0},  # isolated groups at 256 rays
                "full": {"isolated_rays": False}}
    err = residual_label_error(seed, n_inst, variants, quantile=1.0)
    assert err["isolated"] <= 0.01 and err["isolated"] <= err["full"] + 2e-3, err
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n_inst)
    rays = to_mi(*training_rays(rng, scene, 256))
    weights = [mi.Float(rng.normal(size=256).astype(np.float32)) for _ in range(n_inst)]
    out = {}
    for name, opts in variants.items():
        it = make(scene, sharpness=10.0, temperature=0.1, residual=True, **opts)
        out[name] = labels_and_grads(it, lambda it: it.render_rays(*rays), weights) + (it.last_stats["samples"],)
    assert np.abs(out["isolated"][0] - out["full"][0]).max() <= 2e-3
    assert cosine(out["isolated"][1], out["full"][1]) >= 0.999
    assert out["isolated"][2] < 0.95 * out["full"][2]


def test_isolated_residual_rays_need_a_batch_that_pays_for_them():
    """Isolated rays with the residual field get their own sample groups only where they save
    more samples than a group costs (``isolated_group_cost``): none on a 64-ray batch, the
    same samples as with ``isolated_rays`` off."""
    rng = np.random.default_rng(5)
    scene = random_scene(rng, 3)
    rays = to_mi(*training_rays(rng, scene, 64))
    samples = {}
    for name, opts in (("default", {}), ("off", {"isolated_rays": False})):
        it = make(scene, sharpness=10.0, temperature=0.1, residual=True, **opts)
        with dr.suspend_grad():
            dr.eval(it.render_rays(*rays))
        samples[name] = it.last_stats["samples"]
    assert samples["default"] == samples["off"], samples


def test_rays_meeting_one_box_evaluate_only_that_box():
    """Rays aimed at the second of two far-apart boxes evaluate it alone (one SDF evaluation per
    sample). Instance 0 used to be marked as met by every ray meeting any box (an in-place
    ``|=`` on its own mask) and got a band of its own on each of them."""
    scene = {"centre": np.array([[-8.0, 0.5, 15.0], [6.0, 0.5, 15.0]]),
             "size": np.array([[1.8, 1.5, 4.2], [2.0, 1.6, 4.5]]), "yaw": np.array([0.3, -0.4])}
    rng = np.random.default_rng(3)
    d = scene["centre"][1] + rng.uniform(-0.8, 0.8, (64, 3))
    rays = to_mi(np.zeros((64, 3)), d / np.linalg.norm(d, axis=1, keepdims=True), np.zeros(64))
    it = make(scene, sharpness=10.0, temperature=0.1)
    with dr.suspend_grad():
        labels = it.render_rays(*rays)
    assert it.last_stats["rays"] == 64 and it.last_stats["sdf_evals"] == it.last_stats["samples"]
    assert np.all(np.array(labels[0]) == 0.0) and np.all(np.array(labels[1]) > 0.5)


@pytest.mark.slow
@pytest.mark.parametrize("n_inst", [1, 3, 6, 12])
@pytest.mark.parametrize("s", [1.0, 3.0, 10.0])
def test_adaptive_matches_reference_full(n_inst, s):
    out = accuracy_case(n_inst, s, 1024, seed=100 + n_inst, with_grads=True)
    err = np.abs(out["adaptive"][0] - out["ref"][0]).max(0)
    g_ref, g_ad, g_dense = out["ref"][1], out["adaptive"][1], out["dense"][1]
    # the derivative of the converged integral on the first FD_RAYS rays (2 renders per parameter)
    rng = np.random.default_rng(100 + n_inst)
    scene = random_scene(rng, n_inst, dynamic=True)
    o, d, t = training_rays(rng, scene, 1024, max_time=2.0)
    sub = to_mi(o[:FD_RAYS], d[:FD_RAYS], t[:FD_RAYS])
    weights = [mi.Float(rng.normal(size=1024).astype(np.float32)[:FD_RAYS]) for _ in range(n_inst)]
    fd = converged_fd_gradient(scene, sub, weights, s)
    it = make(scene, sharpness=s, temperature=1.0 / s)
    g_ad_sub = labels_and_grads(it, lambda it: it.render_rays(*sub), weights)[1]
    print(f"n={n_inst} s={s} max={err.max():.4f} p99={np.quantile(err, 0.99):.4f} "
          f"cos(ad,ref)={cosine(g_ad, g_ref):.4f} cos(ad,dense)={cosine(g_ad, g_dense):.4f} "
          f"cos(dense,ref)={cosine(g_dense, g_ref):.4f} cos(ad,converged FD)={cosine(g_ad_sub, fd):.4f}")
    # AD of a sampled integral differentiates the samples it has: for the grid reference and
    # dense those are near, not at, each ray's minimum, so only the converged FD is the truth
    assert cosine(g_ad_sub, fd) >= GRAD_COSINE_MIN
    assert err.max() <= FULL_MAX_ABS and np.quantile(err, 0.99) <= FULL_P99_ABS


# ----------------------------------------------------------------------------------------------
# gradients vs finite differences
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("sampling", ["dense", "fixed"])
def test_gradients_match_finite_differences(sampling):
    """AD gradient of a random-weighted loss vs central differences of raw box parameters.

    The integral has no differentiable symbolic loop (sample positions are detached, the sums use
    ``dr.block_prefix_sum`` / ``dr.block_sum``); if one were introduced with a wrong
    ``max_iterations`` hint its gradients would silently go wrong, which this check catches.
    The integrators run with ``ridge_gradients`` off: that option deliberately replaces the
    discrete integral's one-sided gradient at each ray's deepest sample by the envelope gradient
    of the continuous one (checked against central differences of the converged integral in the
    slow accuracy test and ``test_ridge_gradients_follow_the_converged_integral``).
    ``fixed``: the integral on fixed uniform samples; ``dense``: on the dense strategy's own sample
    positions, frozen (they are detached in the integrator, so AD differentiates exactly this; FD
    of the full strategy would also see importance samples jump, which AD by design ignores).
    """
    rng = np.random.default_rng(5)
    scene = random_scene(rng, 3, dynamic=True)
    n_rays, s = 256, 3.0
    rays = to_mi(*training_rays(rng, scene, n_rays, max_time=2.0))
    w = [rng.normal(size=n_rays) for _ in range(3)]
    kw = {"sharpness": s, "temperature": 1.0 / s, "ridge_gradients": False}
    grid_m = 400  # few samples: float32 rounding of long prefix sums would swamp small FDs
    grid = mi.Float(np.tile(np.linspace(0.0, 45.0, grid_m).astype(np.float32), n_rays))

    it = make(scene, sampling="dense", **kw)
    if sampling == "dense":  # the dense strategy's own positions, frozen at the base parameters
        with dr.suspend_grad():
            grid, grid_m = dense_positions(it.context(), it.field.decode(), *rays)
            dr.eval(grid)

    def labels(it):
        return it.integrate_at(it.field.decode(), dr.arange(mi.UInt32, n_rays), *rays, grid, grid_m)

    def loss(values: dict) -> float:
        it = make(scene, sampling="dense", **kw)
        for k, v in values.items():
            it.field.params[k] = mi.Float(v.astype(np.float32))
        with dr.suspend_grad():
            lab = labels(it)
            return float(sum(np.dot(np.array(lab[k], dtype=np.float64), w[k]) for k in range(3)))

    base = {k: np.array(it.field.params[k], dtype=np.float64) for k in BOX_KEYS}
    _, g = labels_and_grads(it, labels, [mi.Float(x.astype(np.float32)) for x in w])
    offsets = np.cumsum([0] + [len(base[k]) for k in BOX_KEYS])
    # eps per parameter: 2 mm of centre, 3 mm of size (1/s = 0.33 m; a 1 cm step already shows the
    # curvature), 2e-3 rad of yaw, 2 mm/frame of velocity
    eps = {"size": 0.003, "centre": 0.002, "yaw": 2e-3, "velocity": 2e-3}
    checks = [("centre", 0), ("centre", 2), ("size", 0), ("size", 5), ("yaw", 0), ("velocity", 0),
              ("velocity", 8)]
    ads, fds = [], []
    for key, i in checks:
        e = eps[key]
        plus, minus = dict(base), dict(base)
        plus[key], minus[key] = base[key].copy(), base[key].copy()
        plus[key][i] += e
        minus[key][i] -= e
        fds.append((loss(plus) - loss(minus)) / (2 * e))
        ads.append(g[offsets[BOX_KEYS.index(key)] + i])
    ads, fds = np.array(ads), np.array(fds)
    print("AD", ads, "FD", fds)
    # per entry within 25 % of the largest checked gradient, and the vectors aligned
    assert np.all(np.abs(ads - fds) <= FD_TOLERANCE * np.abs(fds).max()), (ads, fds)
    assert cosine(ads, fds) >= FD_COSINE_MIN


def converged_fd_gradient(scene: dict, rays, weights, s: float, **kw) -> np.ndarray:
    """Central differences of ``sum weights * labels`` of the converged integral
    (:func:`reference_labels`) w.r.t. every box parameter, steps moving surfaces ~5 mm
    (``kw``: integrator options, e.g. the residual field)."""
    it = make(scene, sampling="dense", sharpness=s, temperature=1.0 / s, **kw)
    w = np.stack([np.array(x, dtype=np.float64) for x in weights])

    def loss() -> float:
        with dr.suspend_grad():
            lab = reference_labels(it, scene, rays, s)[:it.field.n]
            return float((np.stack([np.array(x, dtype=np.float64) for x in lab]) * w).sum())

    return central_differences(it, loss, fd_steps(it.field.n, BenchConfig()))


def test_ridge_gradients_follow_the_converged_integral():
    """With ``ridge_gradients`` the adaptive AD gradient is that of the converged integral
    (central differences of the fine reference); AD's one-sided gradient at the rays' deepest
    samples inside boxes is measurably off on the same rays (so the check can fail)."""
    rng = np.random.default_rng(24)
    scene = random_scene(rng, 3, dynamic=True)
    n_rays, s = 256, 10.0
    rays = to_mi(*training_rays(rng, scene, n_rays, max_time=2.0))
    weights = [mi.Float(rng.normal(size=n_rays).astype(np.float32)) for _ in range(3)]
    fd = converged_fd_gradient(scene, rays, weights, s)
    cos = {}
    for ridge in (True, False):
        it = make(scene, sharpness=s, temperature=1.0 / s, ridge_gradients=ridge)
        cos[ridge] = cosine(labels_and_grads(it, lambda it: it.render_rays(*rays), weights)[1], fd)
    print(f"cos vs converged FD: ridge {cos[True]:.4f} one-sided {cos[False]:.4f}")
    assert cos[True] >= GRAD_COSINE_MIN
    assert cos[False] < cos[True] - 0.05


def test_kink_gradients_follow_the_converged_integral(monkeypatch):
    """With the residual, a moved sample sits exactly at each kink of ``B`` where ``B + R`` has
    a minimum; there the adaptive AD gradient is the envelope of the kink's two faces weighted
    by ``F``'s own slopes, and follows the converged integral (central differences of the fine
    reference; measured 0.9988). With AD's one-sided face gradient at those samples instead
    (the weights dropped) it is measurably off on the same rays (measured 0.9315)."""
    rng = np.random.default_rng(24)
    scene = random_scene(rng, 3, dynamic=True)
    n_rays, s = 256, 10.0
    rays = to_mi(*training_rays(rng, scene, n_rays, max_time=2.0))
    weights = [mi.Float(rng.normal(size=n_rays).astype(np.float32)) for _ in range(3)]
    fd = converged_fd_gradient(scene, rays, weights, s, residual=True)
    minima = residual_search.kink_minima

    def one_sided(*args, **kwargs):
        return [(t, f, dr.full(mi.Float, -1.0, dr.width(t))) for t, f, _ in minima(*args, **kwargs)]

    cos = {}
    for kinks in ("envelope", "one-sided"):
        if kinks == "one-sided":
            monkeypatch.setattr(bands_module, "kink_minima", one_sided)
        it = make(scene, sharpness=s, temperature=1.0 / s, residual=True)
        cos[kinks] = cosine(labels_and_grads(it, lambda it: it.render_rays(*rays), weights)[1], fd)
    print(f"cos vs converged FD: {cos}")
    assert cos["envelope"] >= GRAD_COSINE_MIN
    assert cos["one-sided"] < cos["envelope"] - 0.03


# ----------------------------------------------------------------------------------------------
# robustness
# ----------------------------------------------------------------------------------------------


def finite_labels_and_grads(scene: dict, rays, **kw) -> None:
    for sampling in ("adaptive", "dense"):
        it = make(scene, sampling=sampling, coarse_samples=32, fine_samples=16, **kw)
        n = dr.width(rays[0].x)
        w = [mi.Float(np.linspace(-1, 1, n, dtype=np.float32)) for _ in range(it.field.n)]
        vals, grad = labels_and_grads(it, lambda it: it.render_rays(*rays), w)
        assert np.all(np.isfinite(vals)), sampling
        assert np.all(vals >= -1e-5) and np.all(vals.sum(0) <= 1 + 1e-4), sampling
        assert np.all(np.isfinite(grad)), sampling


@pytest.mark.parametrize("s", [1.0, 100.0, 1e4])
def test_no_nan_extreme_cases(s):
    box = {"centre": np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 10.0], [0.0, 0.0, 100.0], [0.0, 0.0, 140.0]]),
           "size": np.array([[1.8, 1.5, 4.2], [2.0, 1.6, 4.5], [1.8, 1.5, 4.2], [1.8, 1.5, 4.2]]),
           "yaw": np.array([0.0, 0.0, 0.5, 0.0]), "velocity": np.zeros((4, 3)), "dynamic": np.zeros(4)}
    h = 0.5 * box["size"][1]
    c = box["centre"][1]
    o = np.zeros((7, 3))  # the camera sits inside box 0
    targets = np.array([c + [h[0], 0.0, -h[2]], c + [h[0], 0.0, h[2]],       # along a face
                        c + [h[0], h[1], 0.0], [0.0, 0.0, 100.0],              # edge; far box
                        [0.0, 0.0, 150.0], [0.0, 1.0, 5.0], [0.0, -5.0, 1.0]])
    o[0] = c + [h[0], 0.0, -h[2] - 5.0]  # ray 0 runs exactly in the plane of a side face
    o[2] = c + [h[0], h[1], -10.0]       # ray 2 runs exactly along an edge
    d = targets - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = to_mi(o, d, np.zeros(7))
    finite_labels_and_grads(box, rays, sharpness=s, temperature=1.0 / s)


@pytest.mark.parametrize("residual", [False, True])
def test_no_nan_with_tiny_huge_and_turned_boxes(residual):
    """Boxes are what the parameters say (nothing clamps them): a 2 cm box, a 20 m box and yaws
    far outside (-pi, pi] render finite labels (a partition of unity) with finite gradients,
    and the boxes keep their values."""
    scene = {"centre": np.array([[0.0, 0.5, 12.0], [3.0, 0.5, 30.0], [-2.0, 0.5, 9.0]]),
             "size": np.array([[0.02, 0.02, 0.02], [20.0, 20.0, 20.0], [1.8, 1.5, 4.2]]),
             "yaw": np.array([0.0, 40.0, -7.5]), "velocity": np.zeros((3, 3)), "dynamic": np.zeros(3)}
    rng = np.random.default_rng(9)
    rays = to_mi(*training_rays(rng, scene, 96))
    it = make(scene, residual=residual)
    w = [mi.Float(np.ones(96, np.float32))] * 3
    vals, grad = labels_and_grads(it, lambda it: it.render_rays(*rays), w)
    assert np.all(np.isfinite(vals)) and np.all(np.isfinite(grad))
    np.testing.assert_allclose(it.render_rays(*rays)[-1].numpy() + vals.sum(0), 1.0, atol=1e-4)
    assert vals[1].max() > 0.5 and vals[2].max() > 0.5  # the big and the turned box render
    np.testing.assert_allclose(it.boxes()["size"], scene["size"], rtol=1e-6)
    np.testing.assert_allclose(it.boxes()["yaw"], scene["yaw"], rtol=1e-6)


# ----------------------------------------------------------------------------------------------
# Mitsuba plumbing: load_dict, render, traverse, no recompilation
# ----------------------------------------------------------------------------------------------


def small_scene_dict(scene: dict, **kw) -> dict:
    from vsrd_mi.scene.sensors import perspective_sensor
    K = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    return {"type": "scene",
            "integrator": {"type": "vsrd_silhouette", "id": "vsrd", **box_properties(**scene), **kw},
            "sensor": perspective_sensor(K, np.eye(4), (32, 24), 0),
            }


def test_render_traverse_and_no_recompilation():
    rng = np.random.default_rng(4)
    scene = random_scene(rng, 2)
    sc = mi.load_dict(small_scene_dict(scene, residual=True))
    img = mi.render(sc, spp=1)
    assert img.shape == (24, 32, 3 + 3)  # RGB + label_0, label_1, background
    arr = np.array(img)
    assert np.all(np.isfinite(arr))
    np.testing.assert_allclose(arr[..., 3:].sum(-1), 1.0, atol=1e-4)
    params = mi.traverse(sc)
    keys = set(params.keys())
    for k in ("vsrd.centre", "vsrd.size", "vsrd.yaw", "vsrd.velocity", "vsrd.dynamic",
              "vsrd.rdf_embedding", "vsrd.rdf_hyper_w0", "vsrd.sharpness", "vsrd.temperature"):
        assert k in keys, k
    # the boxes in physical units, as given; the residual's parameters only with the field on
    np.testing.assert_allclose(np.array(params["vsrd.size"]), scene["size"].ravel(), rtol=1e-6)
    np.testing.assert_allclose(np.array(params["vsrd.yaw"]), scene["yaw"], rtol=1e-6)
    assert not any("rdf_" in k for k in mi.traverse(mi.load_dict(small_scene_dict(scene))).keys())
    rays = to_mi(*training_rays(rng, scene, 256))
    integ = sc.integrator()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        compiles, seen = [], set()
        # the first pass compiles each band-count group and residual bucket once; the second
        # pass uses nearby values (s + 1e-3 and a new tau: baked-in literals would differ, the
        # shapes do not) and must launch no kernel whose code the first pass did not have.
        # Counted by kernel hash, not by cache misses: a kernel found in the on-disk cache of an
        # earlier run is a cache hit even where it was generated anew
        base = [3.0, 10.0, 13.0, 4.0, 7.0, 11.0, 12.5]
        schedule = base + [v + 1e-3 for v in base]
        for i, s in enumerate(schedule):
            params["vsrd.sharpness"] = s
            params["vsrd.temperature"] = 1.0 / s + 0.01 * (i >= len(base))
            params.update()
            dr.kernel_history()  # clear
            p = integ.field.params["centre"]
            dr.enable_grad(p)
            lab = integ.render_rays(*rays)
            dr.backward(dr.sum(lab[0] * lab[0]))
            g = dr.grad(p)
            dr.eval(g)
            compiles.append(new_kernels(seen))
            integ.field.params["centre"] = dr.detach(p)
            assert np.all(np.isfinite(np.array(g)))
        assert compiles[7:] == [0] * 7, compiles
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_chord_grid_interpolates_the_residual():
    """:class:`ChordGrid` reads the grid values at its nodes, reproduces a quadratic residual
    exactly between them (Catmull-Rom), keeps the box SDF exact and adds the residual only
    where ``B <= reach``; checked against the closed forms."""
    from vsrd_plugins.sdf import box_sdf_local
    rng = np.random.default_rng(5)
    starts, lengths, counts = np.array([2.0, 7.5]), np.array([3.0, 1.2]), np.array([9, 4])
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    quad = [(0.05, -0.01, 0.003), (0.2, 0.04, -0.02)]  # r(t) = a + b (t - start) + c (t - start)^2
    nodes = [s0 + np.linspace(0.0, ln, n) for s0, ln, n in zip(starts, lengths, counts)]
    r = np.concatenate([a + b * (x - s0) + c * (x - s0) ** 2 for (a, b, c), x, s0 in zip(quad, nodes, starts)])
    ol = mi.Vector3f(mi.Float([-3.0, -1.0]), mi.Float([0.2, 0.0]), mi.Float([0.1, -0.3]))
    dl = mi.Vector3f(mi.Float([0.8, 0.6]), mi.Float([0.0, 0.1]), mi.Float([0.6, 0.79]))
    half = mi.Vector3f(mi.Float([1.0, 0.9]), mi.Float([0.8, 0.7]), mi.Float([2.0, 2.2]))
    grid = ChordGrid((ol, dl, half), mi.Float(starts), mi.Float((counts - 1) / lengths),
                     mi.UInt32(counts), mi.UInt32(first), mi.Float(r), 2, mi.UInt32([0, 1]), mi.UInt32([0, 1]))
    pair = np.repeat([0, 1], 50)
    t = np.concatenate([rng.uniform(s0, s0 + ln, 50) for s0, ln in zip(starts, lengths)])
    expected = np.array([quad[p][0] + quad[p][1] * (x - starts[p]) + quad[p][2] * (x - starts[p]) ** 2
                         for p, x in zip(pair, t)])
    np.testing.assert_allclose(np.array(grid.residual(mi.UInt32(pair), mi.Float(t))), expected, atol=2e-6)
    node_pair = np.repeat([0, 1], counts)
    np.testing.assert_allclose(np.array(grid.residual(mi.UInt32(node_pair), mi.Float(np.concatenate(nodes)))),
                               r, atol=1e-6)
    box = np.array(box_sdf_local(dr.gather(mi.Vector3f, ol, mi.UInt32(pair)) + mi.Float(t)
                                 * dr.gather(mi.Vector3f, dl, mi.UInt32(pair)),
                                 dr.gather(mi.Vector3f, half, mi.UInt32(pair))))
    reach = 0.4
    sdf, b = grid.sdf_within(mi.UInt32(pair), mi.Float(t), reach)
    np.testing.assert_allclose(np.array(sdf), box + np.where(box <= reach, expected, 0.0), atol=2e-6)
    np.testing.assert_allclose(np.array(b), box, atol=1e-6)
    np.testing.assert_allclose(np.array(grid.sdf(mi.UInt32(pair), mi.Float(t))), box + expected, atol=2e-6)
    assert (box > reach).any() and (box <= reach).any()  # both sides of the rule were exercised


def test_residual_grid_matches_the_exact_residual_search():
    """The chord grid (``residual_grid``, default) against evaluating the residual at every scan
    point and sample (``residual_grid = 0``): labels within 0.003 (measured 6e-6) and the box
    gradient at cosine >= 0.999 (measured 1.0000) on a 3-box scene, with fewer residual
    evaluations outside the AD graph (measured 0.47x here; 0.34x on the integrator benchmark's
    6 boxes / 16k rays, where a larger share of lanes is frozen)."""
    from vsrd_plugins import sdf as sdf_module
    rng = np.random.default_rng(21)
    scene = random_scene(rng, 3)
    rays = to_mi(*training_rays(rng, scene, 256))
    kw = dict(sharpness=10.0, temperature=0.1, residual=True)
    out, points = {}, {}
    original = sdf_module.ResidualField.evaluate_grouped
    for spacing in (0.0, 0.5):
        counted = []

        def count(self, weights, instances, pts):
            if not dr.grad_enabled(weights) and not any(dr.grad_enabled(p) for p in pts):
                counted.extend(dr.width(p.x) for p in pts)
            return original(self, weights, instances, pts)

        sdf_module.ResidualField.evaluate_grouped = count
        try:
            out[spacing] = labels_and_grads(make(scene, residual_grid=spacing, **kw),
                                            lambda i: i.render_rays(*rays), [1.0, 2.0, 3.0])
        finally:
            sdf_module.ResidualField.evaluate_grouped = original
        points[spacing] = sum(counted)
    assert np.abs(out[0.5][0] - out[0.0][0]).max() <= 3e-3, np.abs(out[0.5][0] - out[0.0][0]).max()
    assert cosine(out[0.5][1], out[0.0][1]) >= 0.999, cosine(out[0.5][1], out[0.0][1])
    assert points[0.5] < 0.6 * points[0.0], (points[0.5], points[0.0])



def test_residual_lattice_matches_the_chord_grid(monkeypatch):
    """Filling the chord grids from the per-instance residual lattice (``residual_lattice``,
    forced here: on 256 rays the integrator would evaluate the chords, which is cheaper there)
    gives the labels of the MLP-filled grids within 2e-3 (measured 3e-5) and the box gradient
    at cosine >= 0.999 (measured 1.0000); nothing recompiles when the boxes change size, which
    changes the lattice's node counts every step."""
    rng = np.random.default_rng(21)
    scene = random_scene(rng, 3)
    rays = to_mi(*training_rays(rng, scene, 256))
    kw = dict(sharpness=10.0, temperature=0.1, residual=True)
    out = {}
    for forced in (False, True):
        if forced:
            monkeypatch.setattr(residual_search, "LATTICE_LOOKUP_COST", -1e9)  # always cheaper
        it = make(scene, residual_lattice=0.35 if forced else 0.0, **kw)
        out[forced] = labels_and_grads(it, lambda i: i.render_rays(*rays), [1.0, 2.0, 3.0])
    assert np.abs(out[True][0] - out[False][0]).max() <= 2e-3, np.abs(out[True][0] - out[False][0]).max()
    assert cosine(out[True][1], out[False][1]) >= 0.999, cosine(out[True][1], out[False][1])
    # one box too: its per-instance tables are width-1 arrays, whose reads a kernel's code can
    # record (they were made from NumPy views once, and compiled anew at random steps)
    single = {key: value[:1] for key, value in scene.items()}
    one = make(single, residual_lattice=0.35, **kw)
    runs = [(it, rays), (one, to_mi(*training_rays(np.random.default_rng(3), single, 256)))]
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for integ, batch in runs:
            size = np.array(integ.field.params["size"])
            seen, compiles = set(), []
            # a first pass compiles each sampling layout once, a second with other sizes (other
            # node counts per box) must compile nothing
            for offset in (0.0, 0.1, 0.2, 0.05, 0.15, 0.25):
                integ.field.params["size"] = mi.Float(size + offset)
                dr.kernel_history()  # clear
                with dr.suspend_grad():
                    dr.eval(integ.render_rays(*batch))
                compiles.append(new_kernels(seen))
            assert compiles[3:] == [0] * 3, (integ.field.n, compiles)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_residual_lattice_extremes_are_finite(monkeypatch):
    """The lattice (forced) with a 5 cm box, a 12 m box, a box 100 m away, a camera inside a box
    and sharpness 3 (a wide margin) to 1e4: labels finite and a partition of unity, gradients
    finite for every box and residual parameter."""
    monkeypatch.setattr(residual_search, "LATTICE_LOOKUP_COST", -1e9)  # always cheaper
    scene = {"centre": np.array([[0.0, 0.5, 8.0], [3.0, 0.5, 12.0], [-2.0, 0.5, 100.0]]),
             "size": np.array([[1.8, 1.5, 4.2]] * 3), "yaw": np.array([0.3, 0.0, -1.0]),
             "velocity": np.zeros((3, 3)), "dynamic": np.zeros(3)}
    rng = np.random.default_rng(12)
    o, d, t = training_rays(rng, scene, 192)
    o[:64] = scene["centre"][0] + rng.uniform(-0.3, 0.3, (64, 3))  # inside the first box
    rays = to_mi(o, d, t)
    for s in (3.0, 10.0, 1e4):
        it = make(scene, residual=True, sharpness=s, temperature=0.1)
        it.field.params["size"] = mi.Float([0.05] * 3 + [12.0] * 3 + [1.8, 1.5, 4.2])
        keys = list(BOX_KEYS) + [f"rdf_{k}" for k in it.field.residual.params]
        params = {k: it.field.params[k] if k in BOX_KEYS else it.field.residual.params[k[4:]] for k in keys}
        for p_ in params.values():
            dr.enable_grad(p_)
        labels = it.render_rays(*rays)
        dr.backward(sum(dr.sum(lab * (i + 1.0)) for i, lab in enumerate(labels[:3])))
        vals = np.stack([np.array(dr.detach(x)) for x in labels])
        assert np.all(np.isfinite(vals)), s
        np.testing.assert_allclose(vals.sum(0), 1.0, atol=1e-4)
        for k, p_ in params.items():
            assert np.all(np.isfinite(np.array(dr.grad(p_)))), (s, k)
        assert vals[:3, 64:].max() > 0.5  # the rays from outside do see the boxes


def test_residual_lattice_only_where_cheaper():
    """The integrator tabulates the residual when the lattice's nodes, plus a lookup per chord
    grid point, cost fewer MLP evaluations than the chord grid's points (a dense ray batch),
    and evaluates the chords otherwise."""
    from vsrd_plugins.sdf import LATTICE_LOOKUP_COST, ResidualLattice
    scene = {"centre": np.array([[0.0, 0.0, 10.0]]), "size": np.array([[1.8, 1.5, 4.2]]), "yaw": np.zeros(1)}
    it = make(scene, residual=True)
    dec = it.field.decode()
    ctx = it.context()
    spacing = it.settings.residual_lattice / ctx.residual_omega()
    extents = np.array([[0.9, 0.75, 2.1]]) + float(np.array(ctx.residual_reach())[0])
    nodes = int(ResidualLattice.node_counts(extents, spacing).prod())
    even = nodes / (1.0 - LATTICE_LOOKUP_COST)  # grid points at which both cost the same
    with dr.suspend_grad():
        assert residual_lattice(ctx, dec, int(0.9 * even)) is None
        lattice = residual_lattice(ctx, dec, int(1.1 * even))
    assert lattice is not None and dr.width(lattice.values) == nodes
    assert residual_lattice(make(scene, residual=True, residual_lattice=0.0).context(), dec, 10 * nodes) is None


def test_pair_scan_evaluates_the_valid_pairs_only():
    """:class:`PairScan` hands ``at`` the valid (slot, ray) pairs alone, block by block, and
    spreads the results back per pair with 0 at the invalid ones (slots beyond a ray's count of
    met boxes, 43 % of the pairs on the 6-box integrator benchmark)."""
    seen = []

    def at(pair, t):
        seen.append(np.array(pair))
        return mi.Float(np.array(pair, dtype=np.float32) * 10.0) + t

    with dr.suspend_grad():
        scan = PairScan.of(mi.Bool([True, False, True, False, True]), at)
        values = scan(mi.Float([0.1, 0.2, 0.3, 1.1, 1.2, 1.3]), 2)
        np.testing.assert_array_equal(seen[0], [0, 2, 4, 0, 2, 4])
        np.testing.assert_allclose(np.array(scan.spread(values, 1)), [1.1, 0.0, 21.2, 0.0, 41.3], atol=1e-6)
        np.testing.assert_allclose(np.array(scan.full(mi.Float([5.0, 6.0, 7.0, 8.0, 9.0]))),
                                   [5.0, 0.0, 27.0, 0.0, 49.0], atol=1e-5)

def sine_cell_scan(cell: int, amp: float, slope: float, kink_between: tuple[int, int] | None = None):
    """A sub-band of ``k = 6`` moved samples over ``[0, 6]`` (one-box residual integrator, two
    rays) and ``F = slope t + 0.5 |t - kink|`` (no kink term without ``kink_between``: the kink
    sits 60 % of the way between those two nominal samples) plus a full sine period of
    amplitude ``amp`` across the cell of nominal sample ``cell``. Returns ``moved(kinks)`` (the
    first ray's moved positions, :func:`snapped_positions`), the sine cell's two extrema of
    ``F``, its width and the kink (``None`` without one)."""
    make({"centre": np.array([[0.0, 0.0, 10.0]]), "size": np.array([[1.8, 1.5, 4.2]]),
               "yaw": np.zeros(1)}, residual=True)
    k, a, b = 6, 0.0, 6.0
    nominal = [float(np.array(sub_sample(mi.Float(a), mi.Float(b), i, k))[0]) for i in range(k + 1)]
    lo, hi = nominal[cell - 1], nominal[cell]
    w = hi - lo
    kink = None if kink_between is None else 0.4 * nominal[kink_between[0]] + 0.6 * nominal[kink_between[1]]

    def f(t):
        bump = np.where((t > lo) & (t < hi), amp * np.sin(2.0 * np.pi * (t - lo) / w), 0.0)
        return slope * t + (0.0 if kink is None else 0.5 * np.abs(t - kink)) + bump

    def at(pair, t):
        return mi.Float(f(np.array(t, dtype=np.float64)).astype(np.float32))

    def moved(kinks=()):
        with dr.suspend_grad():
            sdf = PairScan.of(mi.Bool([True, True]), at)
            out = snapped_positions(sdf, [mi.Float([a, a])], [mi.Float([b, b])], k, k, SCAN,
                                    kinks=[(kt, at(None, kt)) for kt in kinks])[0]
        return np.array([np.array(p)[0] for p in out])

    # F's slope across the sine cell (after the kink where there is one)
    local_slope = slope + (0.0 if kink is None else 0.5)
    phase = np.arccos(-local_slope * w / (2.0 * np.pi * amp))
    extrema = lo + w * np.array([phase, 2.0 * np.pi - phase]) / (2.0 * np.pi)
    return moved, extrema, w, kink


def test_moved_samples_share_a_cell_with_two_extrema():
    """A cell of the snapped sub-bands holding a maximum and a minimum of ``B + R``: both
    extrema claim a sample, the second the next cell's, whose own cell has none
    (:func:`snapped_positions`): both get a sample within a tenth of the cell, and the
    samples stay sorted."""
    moved, extrema, w, _ = sine_cell_scan(3, 0.1, 0.3)
    pos = moved()
    assert np.all(np.diff(pos) >= 0.0), pos
    for x in extrema:
        assert np.min(np.abs(pos - x)) <= 0.1 * w, (x, pos)


def test_moved_samples_take_crowded_extrema_and_kinks():
    """Two extrema of ``B + R`` in the last cell of a sub-band (no sample after it to lend one)
    both get a sample, an earlier one borrowed for the first; a kink where ``F`` has a local
    minimum (``kink``, a hit's deepest point) gets a sample exactly; the samples stay sorted
    (:func:`snapped_positions`). With the kink left out, the scan's parabola across it misses
    it by more."""
    moved, extrema, w, kink = sine_cell_scan(6, 0.3, 0.3, kink_between=(1, 2))
    pos = moved([mi.Float([kink, kink])])
    assert np.all(np.diff(pos) >= 0.0), pos
    for x in extrema:
        assert np.min(np.abs(pos - x)) <= 0.1 * w, (x, pos)
    assert np.min(np.abs(pos - kink)) <= 1e-5, (kink, pos)
    assert np.min(np.abs(moved() - kink)) > 1e-3


def test_moved_samples_sit_on_skewed_extrema():
    """A sharp, skewed minimum of ``B + R`` off the middle of its scan points (a trained
    residual field's): the moved sample lands on it within 2 % of the cell, its value within
    0.02 of the minimum (:meth:`_refined_extrema`'s golden-section steps; the vertex of the
    parabola through the three scan points, the code before, a quarter of a cell off, 0.14 above)."""
    make({"centre": np.array([[0.0, 0.0, 10.0]]), "size": np.array([[1.8, 1.5, 4.2]]),
               "yaw": np.zeros(1)}, residual=True)
    k, a, b = 6, 0.0, 6.0
    lo, hi = [float(np.array(sub_sample(mi.Float(a), mi.Float(b), i, k))[0]) for i in (3, 4)]
    w = hi - lo
    t_min = lo + 0.45 * w  # between the cell's first two scan points (1/3, 2/3)

    def f(t):
        u = t - t_min
        # steep on the left, shallow on the right, a line far from it
        return 0.05 * t - 0.3 * np.exp(-np.where(u < 0.0, (u / (0.05 * w)) ** 2, np.abs(u) / (0.4 * w)))

    def at(pair, t):
        return mi.Float(f(np.array(t, dtype=np.float64)).astype(np.float32))

    with dr.suspend_grad():
        sdf = PairScan.of(mi.Bool([True, True]), at)
        pos = np.array([np.array(p)[0] for p in snapped_positions(
            sdf, [mi.Float([a, a])], [mi.Float([b, b])], k, k, SCAN)[0]])
    assert np.all(np.diff(pos) >= 0.0), pos
    near = pos[np.argmin(np.abs(pos - t_min))]
    assert abs(near - t_min) <= 0.02 * w, (t_min, pos)
    assert f(near) - f(t_min) <= 0.02


def test_moved_samples_see_a_maximum_before_a_kink():
    """A maximum of ``B + R`` just before a kink minimum, with ``F`` rising steeply after the
    kink: the scan points on either side of the maximum and the kink show ``F`` rising, but
    with the kink's value standing in for the scan point beyond it the maximum is an extremum
    and gets a sample (within a tenth of the cell), and the kink one exactly
    (:func:`snapped_positions`; without the kink neither)."""
    make({"centre": np.array([[0.0, 0.0, 10.0]]), "size": np.array([[1.8, 1.5, 4.2]]),
               "yaw": np.zeros(1)}, residual=True)
    k, a, b = 6, 0.0, 6.0
    lo, hi = [float(np.array(sub_sample(mi.Float(a), mi.Float(b), i, k))[0]) for i in (3, 4)]
    w = hi - lo
    t_max, kink = lo + 0.6 * w, lo + 0.75 * w  # scan points of the cell at 1/3, 2/3 and 1

    def f(t):
        before = 0.5 - 2.0 * (t - t_max) ** 2
        return np.where(t <= kink, before, 0.5 - 2.0 * (kink - t_max) ** 2 + 2.0 * (t - kink))

    def at(pair, t):
        return mi.Float(f(np.array(t, dtype=np.float64)).astype(np.float32))

    with dr.suspend_grad():
        sdf = PairScan.of(mi.Bool([True, True]), at)
        kt = mi.Float([kink, kink])
        moved = [np.array([np.array(p)[0] for p in snapped_positions(
            sdf, [mi.Float([a, a])], [mi.Float([b, b])], k, k, SCAN, kinks=kinks)[0]])
            for kinks in ([(kt, at(None, kt))], [])]
    assert np.all(np.diff(moved[0]) >= 0.0), moved[0]
    assert np.min(np.abs(moved[0] - kink)) <= 1e-5, (kink, moved[0])
    assert np.min(np.abs(moved[0] - t_max)) <= 0.1 * w, (t_max, moved[0])
    assert np.min(np.abs(moved[1] - t_max)) > 0.1 * w, (t_max, moved[1])


def test_band_ending_at_its_least_sdf_keeps_that_sample():
    """A hit band that ends at its least ``B + R`` (``hi``, where the band search put it) with
    a maximum of ``B + R`` in the cell before it (trained residual fields): the maximum gets a
    sample and the band's last sample stays at ``hi`` (:meth:`_snapped_slots`,
    :meth:`_sub_bands`). When that sample could move, the maximum took it and the descent
    to the minimum went unsampled (labels off by 0.05)."""
    it = make({"centre": np.array([[0.0, 0.0, 10.0]]), "size": np.array([[1.8, 1.5, 4.2]]),
               "yaw": np.zeros(1)}, residual=True)
    k1, k2 = halves(it.settings.band_samples)
    kp, kq = it.context().tail_samples()
    lo, mid, hi, extra, tail = 0.0, 4.0, 6.0, 8.0, 10.0
    before_last = float(np.array(sub_sample(mi.Float(mid), mi.Float(hi), k2 - 1, k2))[0])
    t_max = before_last + 0.5 * (hi - before_last)

    def f(t):
        bump = 0.3 * np.exp(-(((t - t_max) / (0.2 * (hi - before_last))) ** 2))
        return np.where(t <= hi, 1.0 - 0.1 * t + bump, 1.0 - 0.1 * hi + 2.0 * (t - hi))

    def at(pair, t):
        return mi.Float(f(np.array(t, dtype=np.float64)).astype(np.float32))

    def arr(x):
        return mi.Float([x, x])

    far = arr(-1.0)
    sl = Slot(entry=arr(lo), lo=arr(lo), mid=arr(mid), hi=arr(hi), extra=arr(extra), peak=arr(extra),
              peak_lambda=far, peak_a=arr(0.0), peak_b=arr(0.0), tail_end=arr(tail), deepest=arr(hi))
    with dr.suspend_grad():
        parts = snapped_slots(it.context(), PairScan.of(mi.Bool([True, True]), at), [sl], [])
        sl = replace(sl, moved=tuple(x for part in parts for x in part[0]))
        runs = sub_bands(sl, it.settings.band_samples, kp, kq, snapped=True)
        first, count, value, _ = next(r for r in runs if r[0] == k1 + 1)
        second_half = np.array([np.array(value(mi.UInt32(i)))[0] for i in range(1, count + 1)])
    assert count == k2
    assert second_half[-1] == hi, second_half
    assert np.min(np.abs(second_half - t_max)) <= 0.1 * (hi - before_last), (t_max, second_half)
    assert np.all(np.diff(second_half) >= 0.0), second_half


def test_kink_minima_keep_the_kinks_where_the_sdf_has_a_local_minimum():
    """Of a pair's kinks of ``B`` (ascending), the ones where ``F`` is below its values on either
    side are kept, in order and compacted to the front: ``F`` falls to a kink at 2, rises with
    a steeper slope after a kink at 3.5, falls again to a kink at 5 and rises; a second pair
    has the same ``F`` shifted by 1, and no kinks on its third slot."""
    def f(t):
        return np.where(t < 2.0, 2.0 - t, np.where(t < 3.5, 0.2 * (t - 2.0), np.where(
            t < 4.0, 0.3 + 0.9 * (t - 3.5), np.maximum(0.75 - 0.6 * (t - 4.0), 0.15 + 0.4 * (t - 5.0)))))

    def at(pair, t):
        shift = np.where(np.array(pair) == 1, 1.0, 0.0)
        return mi.Float(f(np.array(t, dtype=np.float64) - shift).astype(np.float32))

    with dr.suspend_grad():
        sdf = PairScan.of(mi.Bool([True, True]), at)
        kinks = [mi.Float([2.0, 3.0]), mi.Float([3.5, 4.5]), mi.Float([5.0, 6.0]), mi.Float([-1.0, -1.0])]
        out = kink_minima(sdf, kinks)
    assert len(out) == KINK_MINIMA == 2
    np.testing.assert_allclose(np.stack([np.array(t) for t, _, _ in out]), [[2.0, 3.0], [5.0, 6.0]])
    np.testing.assert_allclose(np.stack([np.array(v) for _, v, _ in out]), [[0.0, 0.0], [0.15, 0.15]], atol=1e-6)
    # the envelope weight of the face before each kink: slopes -1 | 0.2 and -0.6 | 0.4
    np.testing.assert_allclose(np.stack([np.array(w) for _, _, w in out]), [[0.2 / 1.2] * 2, [0.4 / 1.0] * 2],
                               atol=1e-3)


def test_kink_minima_find_the_minimum_beside_a_sharp_bend():
    """Beside a bend of ``B`` (a ray passing an edge 2 cm away: ``F = sqrt(0.02^2 + (t - 3)^2)
    - 0.3 (t - 3)``, smooth, its minimum 6.3 mm past the bend) the minimum is found to a tenth
    of a millimetre (a parabola through the probes: 0.5 mm off); a bend wider than ``sharpest``
    is left to the scan."""
    rho, g = 0.02, 0.3
    t_min = 3.0 + g * rho / np.sqrt(1.0 - g * g)

    def at(pair, t):
        t = np.array(t, dtype=np.float64)
        return mi.Float((np.sqrt(rho * rho + (t - 3.0) ** 2) - g * (t - 3.0)).astype(np.float32))

    with dr.suspend_grad():
        sdf = PairScan.of(mi.Bool([True, True]), at)
        none = mi.Float([-1.0, -1.0])
        bends = ([mi.Float([3.0, 3.0])] + [none] * 5, [mi.Float([rho, 0.3])] + [mi.Float([1.0, 1.0])] * 5)
        out = kink_minima(sdf, [none], bends, 0.25)
    first, value = np.array(out[0][0]), np.array(out[0][1])
    assert np.all(np.array(out[0][2]) == -1.0)  # beside a bend F is smooth: no envelope
    assert abs(first[0] - t_min) <= 1e-4, (first, t_min)
    assert abs(value[0] - (np.sqrt(rho * rho + (t_min - 3.0) ** 2) - g * (t_min - 3.0))) <= 1e-6, value
    assert first[1] == -1.0 and np.all(np.array(out[1][0]) == -1.0), out


@pytest.mark.parametrize("traceable", [False, True])
def test_golden_minimum_and_illinois_root(traceable):
    """The searches behind the kink minima and the residual peaks, in a symbolic loop or
    unrolled: the minimum of ``cosh(t - c)`` on a bracket around ``c`` and the root of a
    smooth increasing ``g`` (exact values from the closed forms)."""
    c = mi.Float([0.3, -1.2, 2.5])
    t_min = golden_minimum(lambda t: dr.cosh(t - c), c - 0.7, c + 1.1, 24, traceable, "test_golden")
    np.testing.assert_allclose(np.array(t_min), np.array(c), atol=1e-3)

    def g(t):
        return t * t * t + t - c  # increasing; the root of t^3 + t = c

    lo, hi = mi.Float([-2.0, -2.0, -2.0]), mi.Float([2.0, 2.0, 2.0])
    root = np.array(illinois_root(g, lo, hi, g(lo), g(hi), 12, traceable, "test_illinois"))
    np.testing.assert_allclose(root ** 3 + root, np.array(c), atol=1e-5)


def test_residual_peaks_move_to_the_instance_sdfs_crossing():
    """With the residual, a gap peak found on the boxes moves to where the two slots' instance
    SDFs cross (the scene SDF's maximum between them), with the envelope weight of their
    slopes there; a gap whose SDFs do not cross keeps the box peak, and so does one whose box
    peak lies beyond the residual's reach (there the instance SDFs are the boxes')."""
    # two rays, two slots: F_a = 0.5 (t - 1) rising, F_b = 2 - t (ray 0), 4 - t (ray 1) falling
    def at(pair, t):
        p, t = np.array(pair), np.array(t, dtype=np.float64)
        ray, slot = p % 2, p // 2
        fb = np.where(ray == 0, 2.0, 4.0) - t
        return mi.Float(np.where(slot == 0, 0.5 * (t - 1.0), fb).astype(np.float32))

    with dr.suspend_grad():
        sdf = PairScan.of(mi.Bool([True] * 4), at)
        peak = GapPeak(mi.Float([1.2, 2.0]), mi.Bool([True, True]), mi.Float([-1.0, -1.0]),
                       mi.Float([0.0, 0.0]), mi.Float([1.0, 1.0]), mi.Float([0.1, 0.1]))
        far = peak._replace(f=mi.Float([0.6, 0.6]))  # beyond the reach: the box peak stays
        none = GapPeak(mi.Float(0.0), mi.Bool(False), mi.Float(-1.0), mi.Float(0.0), mi.Float(0.0), mi.Float(1e30))
        # ray 1: deepest points 0 and 2, where F_a - F_b stays negative: no crossing in the gap
        ts = [mi.Float([0.5, 0.0]), mi.Float([3.0, 2.0])]
        out = residual_peaks(sdf, [peak, none], ts, 0.5)[0]
        kept = residual_peaks(sdf, [far, none], ts, 0.5)[0]
    np.testing.assert_array_equal(np.array(kept.t), np.float32([1.2, 2.0]))
    t, lam = np.array(out.t), np.array(out.lam)
    assert abs(t[0] - 5.0 / 3.0) <= 1e-4, t  # 0.5 (t - 1) = 2 - t
    assert abs(lam[0] - 1.0 / 1.5) <= 1e-3, lam  # -g_b / (g_a - g_b) = 1 / 1.5
    assert t[1] == np.float32(2.0) and lam[1] == -1.0, (t, lam)


@pytest.mark.parametrize("residual", [False, True])
def test_changing_one_box_compiles_nothing_after_warm_up(residual):
    """One box whose centre, size and yaw change every step (through ``mi.traverse`` and by
    assigning a new array): after the first steps no kernel is new. With one box ``yaw`` holds a
    single value, which Dr.Jit would bake into the kernels as a literal unless the field keeps it
    opaque (5 new kernels every step without)."""
    scene = {"centre": np.array([[0.3, 0.5, 12.0]]), "size": np.array([[1.8, 1.5, 4.2]]), "yaw": np.array([0.4]),
             "velocity": np.zeros((1, 3)), "dynamic": np.zeros(1)}
    sc = mi.load_dict(small_scene_dict(scene, residual=residual))
    params = mi.traverse(sc)
    rng = np.random.default_rng(2)
    rays = to_mi(*training_rays(rng, scene, 512))
    integ = sc.integrator()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        compiles, seen = [], set()
        for step in range(6):
            params["vsrd.centre"] = mi.Float((scene["centre"].ravel() + rng.normal(0, 0.05, 3)).tolist())
            params["vsrd.size"] = mi.Float((scene["size"].ravel() + rng.normal(0, 0.02, 3)).tolist())
            params.update()
            integ.field.params["yaw"] = mi.Float([0.4 + 0.01 * step])  # a new (literal) array, as a user may set
            dr.kernel_history()  # clear
            keys = ("centre", "size", "yaw")
            for k in keys:
                dr.enable_grad(integ.field.params[k])
            lab = integ.render_rays(*rays)
            dr.backward(dr.sum(lab[0] * lab[0]))
            grads = [dr.grad(integ.field.params[k]) for k in keys]
            dr.eval(grads)
            compiles.append(new_kernels(seen))
            for k in keys:
                integ.field.params[k] = dr.detach(integ.field.params[k])
            assert all(np.all(np.isfinite(np.array(g))) for g in grads)
        assert compiles[2:] == [0] * 4, compiles
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
