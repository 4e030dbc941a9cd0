"""The width and length priors' catalogue planes (vsrd_mi.geometry.vehicle_sizes)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant)
from vsrd_mi.geometry import vehicle_sizes
from vsrd_mi.geometry.vehicle_sizes import (CATALOGUE, catalogue_plane, fit_residuals, length_coefficients,
                                           mirror_span, tight_width, typical_length, width_coefficients)


def test_catalogue_is_plausible():
    for v in CATALOGUE:
        assert 3.0 < v.length < 6.5 and 1.1 < v.height < 2.2 and 1.5 < v.width < 2.1, v.model
        # door mirrors add 0.15-0.45 m to a body's width
        assert v.width_mirrors is None or 0.15 <= v.width_mirrors - v.width <= 0.45, v.model
    assert len({v.model for v in CATALOGUE}) == len(CATALOGUE)
    # the city-car segment has models of its own, not one outlier at the end of the plane
    assert sum(v.body == "city car" for v in CATALOGUE) >= 5


def with_mirror_widths() -> list:
    """The catalogue models whose data sheets give a width across the mirrors."""
    return [v for v in CATALOGUE if v.width_mirrors is not None]


def test_plane_is_the_least_squares_fit():
    """The width plane through the vehicles that give a width across the mirrors."""
    design = np.array([[1.0, v.length, v.height] for v in with_mirror_widths()])
    res = fit_residuals()
    # normal equations: the residuals are orthogonal to every column of the design matrix
    np.testing.assert_allclose(design.T @ res, 0.0, atol=1e-9)
    assert np.abs(res).mean() < 0.05 and np.abs(res).max() < 0.12
    _, per_length, per_height = width_coefficients()
    assert per_length > 0 and per_height > 0  # longer and taller vehicles are wider
    # the width plane runs through the 23 models with mirror widths, the first 23 of the catalogue
    assert len(res) == 23 and with_mirror_widths() == list(CATALOGUE[:23])


def test_tight_width_on_numpy_and_drjit_agree():
    lengths, heights = np.array([3.5, 4.3, 5.4]), np.array([1.5, 1.45, 2.0])
    ref = tight_width(lengths, heights)
    got = np.array(tight_width(mi.Float(lengths), mi.Float(heights)))
    np.testing.assert_allclose(got, ref, rtol=1e-6)
    assert ref[0] == pytest.approx(tight_width(3.5, 1.5))
    assert dr.width(tight_width(mi.Float(lengths), mi.Float(heights))) == 3


def test_length_plane_is_the_least_squares_fit_on_width_and_height():
    """The length plane through every catalogue vehicle's body width and height: residuals
    orthogonal to the design (normal equations), wider vehicles longer, and its spread the few
    decimetres that make it a prior for a length nothing measures, not a measurement."""
    design = np.array([[1.0, v.width, v.height] for v in CATALOGUE])
    lengths = np.array([v.length for v in CATALOGUE])
    res = lengths - typical_length(design[:, 1], design[:, 2])
    np.testing.assert_allclose(design.T @ res, 0.0, atol=1e-9)
    assert 0.1 < np.sqrt(np.mean(res ** 2)) < 0.4
    assert length_coefficients()[1] > 0
    # a city car's body width and height give a short car, a van's a long one
    assert typical_length(1.64, 1.49) < 3.8 < 5.0 < typical_length(2.00, 1.99)
    ref = typical_length(np.array([1.9, 2.2]), np.array([1.5, 1.9]))
    np.testing.assert_allclose(np.array(typical_length(mi.Float([1.9, 2.2]), mi.Float([1.5, 1.9]))), ref, rtol=1e-6)


def test_catalogue_plane_fits_the_models_that_give_its_dimensions_and_names_an_unknown_one():
    assert catalogue_plane("length", "width", "height") == length_coefficients()
    # a plane on the widths across the mirrors: the least-squares fit over the models that give one
    design = np.array([[1.0, v.length, v.height] for v in with_mirror_widths()])
    expected, *_ = np.linalg.lstsq(design, [v.width_mirrors for v in with_mirror_widths()], rcond=None)
    np.testing.assert_allclose(catalogue_plane("width_mirrors", "length", "height"), expected, rtol=1e-12)
    with pytest.raises(ValueError, match="wheelbase"):
        catalogue_plane("wheelbase", "length", "height")


def test_mirror_span_names_a_model_without_one():
    assert mirror_span("Fiat 500 (2007)") == pytest.approx(1.89 - 1.63)
    with pytest.raises(ValueError, match="VW up!"):
        mirror_span("VW up! (2011)")
    with pytest.raises(KeyError, match="Trabant"):
        mirror_span("Trabant 601")


def test_catalogue_plane_refuses_too_few_models(monkeypatch):
    monkeypatch.setattr(vehicle_sizes, "CATALOGUE", CATALOGUE[:2])
    with pytest.raises(ValueError, match="only 2 catalogue vehicles"):
        catalogue_plane("length", "width", "height")
