"""How wide a vehicle's tight box is, given its length and height, and how long, given its body
width and height: priors from real vehicles.

A parked car's width is the extent its images show least: seen from behind or in front its mask
box spans ``width * cos(a) + length * sin(a)`` at a viewing angle ``a`` off its axis, and the
projection loss can trade the width against the yaw, the length and the range without changing
any mask box (docs/accuracy.md, "Widths"). Its length and height, by contrast, are fixed by the
masks of the views that pass it. Vehicle widths follow their lengths and heights closely: small
cars are narrow, long and tall vans wide. :func:`tight_width` is the least-squares plane
``width = a + b * length + c * height`` through the 23 models of :data:`CATALOGUE`, the published
dimensions of common European cars, SUVs, vans and pickups, whose data sheets give the width with
the door mirrors unfolded, which is what a tight box holds. Its residuals over those models are a
few centimetres (:func:`fit_residuals`).

A car seen end-on in every view (driving ahead of the camera or towards it) is the other way
round: its masks show its width and height but nothing of its length. :func:`typical_length` is
the least-squares plane ``length = a + b * body_width + c * height`` through all 43 models, a far
looser relation (0.26 m rms: vans and pickups of one width and height differ by a metre), and
:func:`length_given_height` the line of the length on the height alone, for a length bounded from
below (docs/accuracy.md). The length plane takes the body width, mirrors left out: every model's
body width is published, so the plane can be fitted on every segment (the widths across the mirrors
are known for fewer models), and the mirrors' span varies from model to model independently of the
length.

The first 23 models were written down before any synthetic or real sequence was run with the
prior. The other 20, the best-selling models of the segments those left thin (the first 23 had one
A-segment car), were added when the development sets' end-on city cars came out long: chosen by
segment, not by their effect on any sequence, and nothing here is fitted to a sequence.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np


#: Fewest catalogue models that fix a plane in two dimensions.
MIN_PLANE_MODELS = 3


@dataclass(frozen=True)
class VehicleDimensions:
    """Published exterior dimensions of one vehicle model (metres)."""

    model: str
    body: str
    length: float
    height: float
    #: Body width, mirrors folded or left out.
    width: float
    #: Width across the unfolded door mirrors: the tight box's width; None where the data sheet
    #: does not give it (the width plane leaves those models out).
    width_mirrors: float | None = None


#: Manufacturers' published figures, rounded to the centimetre (one body style and generation
#: each), written down from the data sheets as recalled, not checked against them here. Widths
#: across the mirrors are published less consistently than the other dimensions; a few here may
#: be off by a few centimetres, which the plane's fit averages over.
CATALOGUE: tuple[VehicleDimensions, ...] = (
    VehicleDimensions("Fiat 500 (2007)", "city car", 3.55, 1.49, 1.63, 1.89),
    VehicleDimensions("Toyota Yaris (2020)", "city car", 3.94, 1.50, 1.75, 1.96),
    VehicleDimensions("VW Polo (2017)", "hatchback", 4.05, 1.46, 1.75, 1.96),
    VehicleDimensions("VW Golf VII (2013)", "hatchback", 4.26, 1.45, 1.80, 2.03),
    VehicleDimensions("VW Golf VIII (2020)", "hatchback", 4.28, 1.49, 1.79, 2.07),
    VehicleDimensions("Ford Focus (2018)", "hatchback", 4.38, 1.45, 1.83, 2.01),
    VehicleDimensions("Skoda Octavia Combi (2020)", "estate", 4.69, 1.47, 1.83, 2.00),
    VehicleDimensions("VW Passat (2015)", "sedan", 4.77, 1.46, 1.83, 2.08),
    VehicleDimensions("BMW 3 Series (2019)", "sedan", 4.71, 1.44, 1.83, 2.07),
    VehicleDimensions("Mercedes E-Class (2016)", "sedan", 4.92, 1.47, 1.85, 2.07),
    VehicleDimensions("Tesla Model 3 (2017)", "sedan", 4.69, 1.44, 1.85, 2.09),
    VehicleDimensions("Tesla Model S (2012)", "sedan", 4.97, 1.45, 1.96, 2.19),
    VehicleDimensions("Tesla Model Y (2020)", "suv", 4.75, 1.62, 1.92, 2.13),
    VehicleDimensions("VW Tiguan (2016)", "suv", 4.49, 1.67, 1.84, 2.10),
    VehicleDimensions("BMW X5 (2018)", "suv", 4.92, 1.75, 2.00, 2.22),
    VehicleDimensions("Volvo XC90 (2015)", "suv", 4.95, 1.78, 1.96, 2.14),
    VehicleDimensions("Porsche 911 (2019)", "sports", 4.52, 1.30, 1.85, 2.02),
    VehicleDimensions("Mazda MX-5 (2015)", "sports", 3.92, 1.24, 1.74, 1.93),
    VehicleDimensions("Renault Kangoo (2008)", "van", 4.28, 1.80, 1.83, 2.14),
    VehicleDimensions("VW Transporter T6 (2015)", "van", 4.90, 1.99, 1.90, 2.30),
    VehicleDimensions("Ford Transit Custom (2012)", "van", 4.97, 1.98, 1.99, 2.27),
    VehicleDimensions("Ford Ranger (2019)", "pickup", 5.36, 1.82, 1.86, 2.16),
    VehicleDimensions("Toyota Hilux (2016)", "pickup", 5.33, 1.82, 1.86, 2.15),
    # The commonest models of the European segments the models above leave thin (A- and
    # B-segment cars, compact SUVs, compact vans, pickups): length, height and body width only.
    VehicleDimensions("VW up! (2011)", "city car", 3.54, 1.48, 1.64),
    VehicleDimensions("Kia Picanto (2017)", "city car", 3.60, 1.49, 1.60),
    VehicleDimensions("Hyundai i10 (2019)", "city car", 3.67, 1.48, 1.68),
    VehicleDimensions("Toyota Aygo (2014)", "city car", 3.46, 1.46, 1.62),
    VehicleDimensions("Renault Twingo (2014)", "city car", 3.60, 1.55, 1.65),
    VehicleDimensions("Fiat Panda (2012)", "city car", 3.65, 1.55, 1.64),
    VehicleDimensions("Renault Clio (2019)", "hatchback", 4.05, 1.44, 1.80),
    VehicleDimensions("Peugeot 208 (2019)", "hatchback", 4.06, 1.43, 1.75),
    VehicleDimensions("Skoda Fabia (2014)", "hatchback", 3.99, 1.47, 1.73),
    VehicleDimensions("Opel Corsa (2019)", "hatchback", 4.06, 1.44, 1.77),
    VehicleDimensions("Nissan Qashqai (2014)", "suv", 4.38, 1.59, 1.81),
    VehicleDimensions("Dacia Duster (2018)", "suv", 4.34, 1.69, 1.80),
    VehicleDimensions("Kia Sportage (2016)", "suv", 4.48, 1.64, 1.86),
    VehicleDimensions("Audi A4 (2015)", "sedan", 4.73, 1.43, 1.84),
    VehicleDimensions("Skoda Superb (2015)", "sedan", 4.86, 1.47, 1.86),
    VehicleDimensions("Mercedes Vito (2014)", "van", 4.90, 1.91, 1.93),
    VehicleDimensions("VW Caddy (2020)", "van", 4.50, 1.82, 1.86),
    VehicleDimensions("Citroen Jumpy (2016)", "van", 4.96, 1.90, 1.92),
    VehicleDimensions("Nissan Navara (2015)", "pickup", 5.26, 1.84, 1.85),
    VehicleDimensions("Mitsubishi L200 (2015)", "pickup", 5.29, 1.78, 1.82),
)


def catalogue_plane(target: str, first: str, second: str) -> tuple[float, float, float]:
    """``(a, b, c)`` of the least-squares plane ``target = a + b * first + c * second`` through
    the :data:`CATALOGUE` vehicles that give all three, each a :class:`VehicleDimensions` field
    name."""
    known = {f.name for f in fields(VehicleDimensions)} - {"model", "body"}
    unknown = [name for name in (target, first, second) if name not in known]
    if unknown:
        raise ValueError(f"catalogue_plane: {unknown} are not dimensions of a catalogue vehicle {sorted(known)}")
    rows = [v for v in CATALOGUE if all(getattr(v, name) is not None for name in (target, first, second))]
    if len(rows) < MIN_PLANE_MODELS:
        raise ValueError(f"catalogue_plane: only {len(rows)} catalogue vehicles give {target}, {first} and {second}; "
                         f"a plane needs {MIN_PLANE_MODELS}")
    design = np.array([[1.0, getattr(v, first), getattr(v, second)] for v in rows])
    values = np.array([getattr(v, target) for v in rows])
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    return float(coef[0]), float(coef[1]), float(coef[2])


@lru_cache(maxsize=1)
def width_coefficients() -> tuple[float, float, float]:
    """``(a, b, c)`` of the least-squares plane ``width_mirrors = a + b * length + c * height``
    through the :data:`CATALOGUE` models that give a width across the mirrors."""
    return catalogue_plane("width_mirrors", "length", "height")


def tight_width(length, height):
    """Expected width (m, mirrors included) of a vehicle of the given length and height (m).

    Works on floats, NumPy arrays and Dr.Jit arrays alike (a plane in ``length`` and ``height``).
    """
    a, b, c = width_coefficients()
    return a + b * length + c * height


@lru_cache(maxsize=1)
def length_coefficients() -> tuple[float, float, float]:
    """``(a, b, c)`` of the least-squares plane ``length = a + b * width + c * height`` (body
    width, mirrors left out) through :data:`CATALOGUE`."""
    return catalogue_plane("length", "width", "height")


def typical_length(body_width, height):
    """Expected length (m) of a vehicle of the given body width (mirrors left out) and height (m).

    Works on floats, NumPy arrays and Dr.Jit arrays alike (a plane in ``body_width`` and ``height``).
    """
    a, b, c = length_coefficients()
    return a + b * body_width + c * height


@lru_cache(maxsize=1)
def length_given_height() -> tuple[float, float, float]:
    """``(a, b, sd)``: the least-squares line ``length = a + b * height`` through
    :data:`CATALOGUE` and the standard deviation of its residuals (m). Taller vehicles are longer
    (SUVs, vans, pickups), but height says little of a length: saloons and city cars share one
    (the residuals' spread is 0.45 m over the 43 models). A prior for a length nothing else
    measures."""
    design = np.array([[1.0, v.height] for v in CATALOGUE])
    target = np.array([v.length for v in CATALOGUE])
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    residuals = target - design @ coef
    return float(coef[0]), float(coef[1]), float(np.sqrt(np.mean(residuals ** 2)))


def mirror_span(model: str) -> float:
    """Width the door mirrors add to the body of catalogue vehicle ``model`` (m); KeyError naming
    the model when the catalogue has no such vehicle, ValueError when it has no width across the
    mirrors for it."""
    for v in CATALOGUE:
        if v.model == model:
            if v.width_mirrors is None:
                raise ValueError(f"the catalogue gives no width across the mirrors for {model!r}")
            return v.width_mirrors - v.width
    raise KeyError(f"vehicle {model!r} is not in the catalogue")


def fit_residuals() -> np.ndarray:
    """Catalogue widths (mirrors included) less :func:`tight_width` of their lengths and heights
    (m), over the vehicles that give a width across the mirrors."""
    return np.array([v.width_mirrors - tight_width(v.length, v.height) for v in CATALOGUE
                     if v.width_mirrors is not None])


__all__ = ["CATALOGUE", "MIN_PLANE_MODELS", "VehicleDimensions", "catalogue_plane", "fit_residuals",
           "length_coefficients", "length_given_height", "mirror_span", "tight_width", "typical_length",
           "width_coefficients"]
