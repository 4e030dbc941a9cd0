"""Stereo points against a box's footprint, along their viewing rays (NumPy and Dr.Jit).

Stereo depth errors lie along the viewing ray and grow with the square of the range, so a point is
compared with the entry point of its own ray (camera -> point) into the box's footprint rectangle
rather than with the nearest face: the residual is the range difference, scaled by
``(reference_range / range)^2`` (the equivalent error at ``reference_range``). A ray that misses
the rectangle gets the distance of the rectangle from the ray's line (how far the box is off the
observed silhouette), unscaled. The initialisation fits a footprint's centre with it
(:func:`vsrd_mi.init.attributes.fit_footprint`) and the optimisation keeps parked boxes on their
visible surface with it (:class:`vsrd_mi.optimise.losses.VisibleSurface`); docs/method.md §4 and §6.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from scipy.optimize import brentq
from scipy.special import erfcx

from .xp import NP

#: Ray direction components smaller than this are replaced by it in the slab test (a ray parallel
#: to a face: its entry distances become huge instead of infinite, so no gradient meets 0 * inf).
MIN_DIRECTION = 1e-12
#: Ranges below this (m) are clamped in the scaling (a point at its own camera).
MIN_RANGE = 1e-9


def _slab(x, z, cam_x, cam_z, half_x, half_z, xp):
    """Range, unit direction, entry and exit distances of each ray (camera -> point) through the
    rectangle (the slab method), and whether it meets it ahead of the camera."""
    rx, rz = x - cam_x, z - cam_z
    rng = xp.maximum(xp.sqrt(rx * rx + rz * rz), MIN_RANGE)
    dx, dz = rx / rng, rz / rng
    sx = xp.where(xp.abs(dx) > MIN_DIRECTION, dx, MIN_DIRECTION)
    sz = xp.where(xp.abs(dz) > MIN_DIRECTION, dz, MIN_DIRECTION)
    ax, bx = (-half_x - cam_x) / sx, (half_x - cam_x) / sx
    az, bz = (-half_z - cam_z) / sz, (half_z - cam_z) / sz
    t_near = xp.maximum(xp.minimum(ax, bx), xp.minimum(az, bz))
    t_far = xp.minimum(xp.maximum(ax, bx), xp.maximum(az, bz))
    hit = (t_near <= t_far) & (t_far > 0)
    return rng, dx, dz, t_near, t_far, hit


def _line_offset(cam_x, cam_z, dx, dz, half_x, half_z, xp):
    """Smallest distance of the rectangle's corners from each ray's line (normal ``(-dz, dx)``)."""
    off = None
    for cx in (-half_x, half_x):
        for cz in (-half_z, half_z):
            o = xp.abs((cz - cam_z) * dx - (cx - cam_x) * dz)
            off = o if off is None else xp.minimum(off, o)
    return off


def footprint_ray_residuals(x, z, cam_x, cam_z, half_x, half_z, reference_range: float,
                            xp: SimpleNamespace = NP):
    """Residuals of points ``(x, z)`` seen from cameras ``(cam_x, cam_z)`` against the rectangle
    ``|x| <= half_x, |z| <= half_z`` (all box-local, metres; arrays of one length or scalars).

    A ray that enters the rectangle: ``(range - entry) * (reference_range / range)^2``, positive
    when the point lies behind the entry face. A ray that misses it: the smallest distance of the
    rectangle's corners from the ray's line. ``xp`` is :data:`vsrd_mi.geometry.xp.NP` or
    :func:`vsrd_mi.geometry.xp.drjit_namespace` (differentiable in the box's pose and size).
    """
    rng, dx, dz, t_near, _, hit = _slab(x, z, cam_x, cam_z, half_x, half_z, xp)
    scale = reference_range / rng
    along = (rng - xp.maximum(t_near, 0.0)) * scale * scale
    return xp.where(hit, along, _line_offset(cam_x, cam_z, dx, dz, half_x, half_z, xp))


def soft_l1(r, scale: float, xp: SimpleNamespace = NP):
    """``scale (sqrt(1 + (r / scale)^2) - 1)``: ``r^2 / (2 scale)`` near 0, ``|r| - scale`` far
    (metres in, metres out; half of SciPy's ``soft_l1`` loss divided by ``scale``)."""
    z = r / scale
    return scale * (xp.sqrt(1.0 + z * z) - 1.0)


def quantile_soft_l1(r, scale: float, quantile: float, xp: SimpleNamespace = NP):
    """:func:`soft_l1` weighted ``1 - quantile`` for residuals ``r < 0`` (a point in front of the
    face its ray enters) and ``quantile`` for the others. Its minimiser is a quantile of the
    residuals where they spread much wider than ``scale`` and an expectile where they lie within
    it: below 0.5 it leaves fewer points in front of the faces than behind them, ``quantile`` of
    them or somewhat more. 0.5 is half the symmetric soft L1."""
    return xp.where(r < 0.0, 1.0 - quantile, quantile) * soft_l1(r, scale, xp)


def _face_quantile(a):
    """``P(offset + noise < 0)`` for an exponential offset of mean 1 and Gaussian noise of standard
    deviation ``a``: ``(1 - erfcx(a / sqrt 2)) / 2`` (0 at ``a = 0``, towards 0.5 as ``a`` grows)."""
    return 0.5 * (1.0 - erfcx(np.asarray(a, dtype=np.float64) / math.sqrt(2.0)))


def range_quantile(ranges, quantile: float, reference_range: float, floor: float = 0.0) -> np.ndarray:
    """Per point, the quantile of the depths at which the face its ray enters lies, for points at
    ``ranges`` (m), given that it is ``quantile`` at ``reference_range``.

    A point's depth along its ray is the face's, plus how far the body lies behind the tight box
    there (exponential, mean ``mu``: mirrors, bumpers and arches stand out, panels curve in), plus
    stereo noise ``N(0, sigma^2)`` with ``sigma`` growing with the square of the range. The face
    then lies at the quantile ``P(offset + noise < 0) = (1 - erfcx(a / sqrt 2)) / 2`` of the
    depths, ``a = sigma / mu``: near 0 where the noise is small against the offsets, towards 0.5
    (the median) where it dwarfs them. ``quantile`` at ``reference_range`` fixes ``a`` there, and
    ``a`` grows as ``(range / reference_range)^2``. A ``quantile`` of 0.5 or more is returned
    unchanged at every range. No point's quantile is below ``floor``: the model has no outliers,
    but stereo mismatches (mixed pixels at a mask's edge, an occluder's disparity) are a share of
    every cloud, and a face at a quantile below their share sits on them.
    """
    ranges = np.asarray(ranges, dtype=np.float64)
    if quantile >= 0.5:
        return np.full(ranges.shape, float(quantile))
    a_ref = brentq(lambda a: float(_face_quantile(a)) - quantile, 0.0, 1e3)
    return np.maximum(_face_quantile(a_ref * (np.maximum(ranges, MIN_RANGE) / reference_range) ** 2), floor)
