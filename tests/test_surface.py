"""Stereo points against a box footprint along their viewing rays (vsrd_mi.geometry.surface).

Checked against an independent construction: the entry and exit of a ray are found by marching
along it in fine steps and testing the rectangle's inequalities directly; the NumPy and Dr.Jit
namespaces must agree.
"""

from __future__ import annotations

import numpy as np
import pytest
import vsrd_mi  # noqa: F401  (selects the Mitsuba variant)

from vsrd_mi.geometry.surface import footprint_ray_residuals, range_quantile
from vsrd_mi.geometry.xp import drjit_namespace

HALF = (0.9, 2.2)
MARCH_STEP = 1e-4


def marched(point, camera, half) -> tuple[float, float] | None:
    """Entry and exit distances of the ray camera -> point through ``|x| <= half`` by marching."""
    d = (point - camera) / np.linalg.norm(point - camera)
    t = np.arange(0.0, 80.0, MARCH_STEP)
    p = camera[None] + t[:, None] * d[None]
    inside = np.flatnonzero(np.all(np.abs(p) <= np.asarray(half), axis=1))
    return (t[inside[0]], t[inside[-1]]) if len(inside) else None


def random_rays(rng, count: int):
    """Cameras 5-30 m from the box in random directions, points near the rectangle."""
    ang = rng.uniform(0, 2 * np.pi, count)
    cams = np.stack([np.cos(ang), np.sin(ang)], 1) * rng.uniform(5, 30, (count, 1))
    pts = rng.uniform(-1.5, 1.5, (count, 2)) * np.array([HALF[0] + 0.3, HALF[1] + 0.3])
    return pts, cams


def test_residuals_match_a_marched_ray():
    rng = np.random.default_rng(3)
    pts, cams = random_rays(rng, 60)
    ref = 10.0
    res = footprint_ray_residuals(pts[:, 0], pts[:, 1], cams[:, 0], cams[:, 1], *HALF, ref)
    hits = 0
    for k in range(len(pts)):
        rng_k = np.linalg.norm(pts[k] - cams[k])
        span = marched(pts[k], cams[k], HALF)
        if span is None:  # missed: the rectangle's distance from the line
            assert res[k] > 0
            continue
        hits += 1
        scale = (ref / rng_k) ** 2
        assert res[k] == pytest.approx((rng_k - span[0]) * scale, abs=2 * MARCH_STEP * scale)
        inside = np.all(np.abs(pts[k]) <= HALF)
        assert (rng_k >= span[0] - MARCH_STEP and rng_k <= span[1] + MARCH_STEP) == inside
    assert 15 < hits < 60


def test_a_missed_ray_gives_the_rectangle_distance_from_its_line():
    # camera at (5, 0) looking along +z: the line x = 5 passes 4.1 m from the corner (0.9, *)
    r = footprint_ray_residuals(np.array([5.0]), np.array([10.0]), np.array([5.0]), np.array([0.0]), *HALF, 10.0)
    assert r[0] == pytest.approx(5.0 - HALF[0])


def test_drjit_namespace_gives_the_numpy_values():
    import mitsuba as mi
    rng = np.random.default_rng(4)
    pts, cams = random_rays(rng, 200)
    f = [mi.Float(c.tolist()) for c in (pts[:, 0], pts[:, 1], cams[:, 0], cams[:, 1])]
    want = footprint_ray_residuals(pts[:, 0], pts[:, 1], cams[:, 0], cams[:, 1], *HALF, 10.0)
    got = np.array(footprint_ray_residuals(*f, *HALF, 10.0, xp=drjit_namespace()))
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


def test_range_quantile_is_the_faces_quantile_of_offset_plus_noise():
    """The quantile holds at the reference range, rises with range towards the median and falls
    towards 0 nearer; at every range it is the share of depths in front of the face when the body
    lies an exponential offset behind it and stereo noise grows with the square of the range
    (Monte Carlo with the noise scale ``range_quantile`` implies at the reference range)."""
    ranges = np.array([2.0, 5.0, 10.0, 20.0, 40.0, 80.0])
    q = range_quantile(ranges, 0.1, 10.0)
    assert q[2] == pytest.approx(0.1, abs=1e-9)
    assert np.all(np.diff(q) > 0) and q[0] < 0.01 and 0.45 < q[-1] < 0.5
    np.testing.assert_array_equal(range_quantile(ranges, 0.5, 10.0), 0.5)
    # the noise scale at the reference range (in units of the mean offset) that gives 0.1 there
    rng = np.random.default_rng(3)
    offsets = rng.exponential(1.0, 400_000)
    normal = rng.standard_normal(400_000)
    scales = np.linspace(0.05, 1.0, 400)
    share = [np.mean(offsets + a * normal < 0) for a in scales]
    a_ref = scales[np.argmin(np.abs(np.array(share) - 0.1))]
    for r, want in zip(ranges, q):
        a = a_ref * (r / 10.0) ** 2
        assert np.mean(offsets + a * normal < 0) == pytest.approx(want, abs=0.01), r


def test_range_quantile_floor_holds_only_where_the_model_falls_below_it():
    """With ``floor`` = the reference quantile, nearer points keep it (the model's 0.03 at 5 m
    would sit on stereo outliers) and further ones follow the model unchanged."""
    ranges = np.array([2.0, 5.0, 10.0, 20.0, 40.0])
    free = range_quantile(ranges, 0.1, 10.0)
    floored = range_quantile(ranges, 0.1, 10.0, floor=0.1)
    assert free[1] < 0.05
    np.testing.assert_allclose(floored[:3], 0.1, atol=1e-9)
    np.testing.assert_array_equal(floored[3:], free[3:])
    np.testing.assert_array_equal(range_quantile(ranges, 0.5, 10.0, floor=0.1), 0.5)
