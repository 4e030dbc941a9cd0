"""Stereo points against a box footprint along their viewing rays (vsrd_mi.geometry.surface).

Checked against an independent construction: the entry and exit of a ray are found by marching
along it in fine steps and testing the rectangle's inequalities directly; the NumPy and Dr.Jit
namespaces must agree.
"""

from __future__ import annotations

import numpy as np
import pytest
import vsrd_mi  # noqa: F401  (selects the Mitsuba variant)

from vsrd_mi.geometry.surface import footprint_ray_residuals
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
