"""The width and length priors' catalogue planes (vsrd_mi.geometry.vehicle_sizes)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant)
from vsrd_mi.geometry.vehicle_sizes import (CATALOGUE, catalogue_plane, fit_residuals, length_coefficients, tight_width,
                                           typical_length, width_coefficients)


def test_catalogue_is_plausible():
    for v in CATALOGUE:
        assert 3.0 < v.length < 6.5 and 1.1 < v.height < 2.2, v.model
        # door mirrors add 0.15-0.45 m to a body's width
        assert 0.15 <= v.width_mirrors - v.width <= 0.45, v.model


def test_plane_is_the_least_squares_fit():
    design = np.array([[1.0, v.length, v.height] for v in CATALOGUE])
    res = fit_residuals()
    # normal equations: the residuals are orthogonal to every column of the design matrix
    np.testing.assert_allclose(design.T @ res, 0.0, atol=1e-9)
    assert np.abs(res).mean() < 0.05 and np.abs(res).max() < 0.12
    _, per_length, per_height = width_coefficients()
    assert per_length > 0 and per_height > 0  # longer and taller vehicles are wider


def test_tight_width_on_numpy_and_drjit_agree():
    lengths, heights = np.array([3.5, 4.3, 5.4]), np.array([1.5, 1.45, 2.0])
    ref = tight_width(lengths, heights)
    got = np.array(tight_width(mi.Float(lengths), mi.Float(heights)))
    np.testing.assert_allclose(got, ref, rtol=1e-6)
    assert ref[0] == pytest.approx(tight_width(3.5, 1.5))
    assert dr.width(tight_width(mi.Float(lengths), mi.Float(heights))) == 3


def test_length_plane_is_the_least_squares_fit_on_width_and_height():
    """The length plane through the catalogue's tight widths and heights: residuals orthogonal to
    the design (normal equations), wider vehicles longer, and its spread the few decimetres that
    make it a prior for a length nothing measures, not a measurement."""
    design = np.array([[1.0, v.width_mirrors, v.height] for v in CATALOGUE])
    lengths = np.array([v.length for v in CATALOGUE])
    res = lengths - typical_length(design[:, 1], design[:, 2])
    np.testing.assert_allclose(design.T @ res, 0.0, atol=1e-9)
    assert 0.1 < np.sqrt(np.mean(res ** 2)) < 0.4
    assert length_coefficients()[1] > 0
    # a city car's width and height give a short car, a van's a long one
    assert typical_length(1.89, 1.49) < 3.9 < 5.0 < typical_length(2.30, 1.99)
    ref = typical_length(np.array([1.9, 2.2]), np.array([1.5, 1.9]))
    np.testing.assert_allclose(np.array(typical_length(mi.Float([1.9, 2.2]), mi.Float([1.5, 1.9]))), ref, rtol=1e-6)


def test_catalogue_plane_names_an_unknown_dimension():
    assert catalogue_plane("length", "width_mirrors", "height") == length_coefficients()
    with pytest.raises(ValueError, match="wheelbase"):
        catalogue_plane("wheelbase", "length", "height")
