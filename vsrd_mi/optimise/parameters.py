"""The optimiser's latent variables of the boxes, and their decoding into physical boxes.

The ``vsrd_silhouette`` integrator's box parameters are physical (``centre``, ``size``, ``yaw``,
``velocity``). The optimiser does not step them directly: it keeps latent variables whose
decoding keeps every box within :class:`BoxRanges` and its yaw a plain angle, steps those with
Adam and, every step, writes the decoded physical values (with their AD graph) into the
integrator's parameters through ``mi.traverse``:

==============  =====  =======================================================================
latent          size   decoding
==============  =====  =======================================================================
``box_dims``    3N     half extents ``h = lo + (hi - lo) sigmoid(raw)``; ``size = 2 h``
``box_centre``  3N     ``centre = lo + (hi - lo) sigmoid(raw)``
``box_yaw``     2N     an unnormalised ``(cos, sin)`` pair; ``yaw = atan2(sin, cos)``
``box_velocity`` 3N    the velocity itself
``box_corner``  N      the plan-corner cut of the car profile (optional, not an integrator
                       parameter): ``corner = max sigmoid(gain raw)`` (:class:`CornerRange`)
==============  =====  =======================================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import drjit as dr
import mitsuba as mi
import numpy as np

from vsrd_plugins.common import sigmoid

from .config import CarProfile
from .losses import to_float

#: Latent variables of the box shape and placement (one Adam), and of the velocity (another).
BOX_LATENTS = ("box_dims", "box_centre", "box_yaw")
VELOCITY_LATENT = "box_velocity"
#: Latent of the fitted plan-corner cut (with the box latents' Adam, when fitted).
CORNER_LATENT = "box_corner"
#: Probability clip of :func:`logit` (keeps a box on a range bound at a finite latent value).
LOGIT_EPS = 1e-6
#: Below this squared norm a ``(cos, sin)`` latent pair decodes as yaw 0 (with no gradient).
YAW_PAIR_MIN_SQUARED = 1e-16


def logit(p: np.ndarray, eps: float = LOGIT_EPS) -> np.ndarray:
    """Inverse of the sigmoid (NumPy), clipped away from 0 and 1 by ``eps``."""
    p = np.clip(np.asarray(p, dtype=np.float64), eps, 1.0 - eps)
    return np.log(p) - np.log1p(-p)


@dataclass(frozen=True)
class BoxRanges:
    """Ranges of the box latents (widened from the paper's to cover real vehicles).

    Half extents (x = width, y = height, z = length): full sizes 1.1-2.7 m wide, 1.0-3.3 m high,
    2.2-7.2 m long, covering city cars (2.5 m), low sports cars (1.16 m high), pickups and vans
    (5.2-6 m long, 2.3 m wide). Centres: +-60 m laterally, -5..8 m vertically (y down, camera at
    0), -5..110 m forward.
    """

    half_lo: tuple[float, float, float] = (0.55, 0.5, 1.1)
    half_hi: tuple[float, float, float] = (1.35, 1.65, 3.6)
    centre_lo: tuple[float, float, float] = (-60.0, -5.0, -5.0)
    centre_hi: tuple[float, float, float] = (60.0, 8.0, 110.0)

    def encode(self, centre: np.ndarray, size: np.ndarray, yaw: np.ndarray,
               velocity: np.ndarray) -> dict[str, np.ndarray]:
        """Latent values (flat, float64) of boxes given as ``centre`` (N, 3), ``size`` (N, 3),
        ``yaw`` (N,) and ``velocity`` (N, 3); sizes and centres outside the ranges are clipped
        to just inside them."""
        lo, hi = np.array(self.half_lo), np.array(self.half_hi)
        half = 0.5 * np.asarray(size, dtype=np.float64).reshape(-1, 3)
        clo, chi = np.array(self.centre_lo), np.array(self.centre_hi)
        yaw = np.asarray(yaw, dtype=np.float64).ravel()
        return {"box_dims": logit((half - lo) / (hi - lo)).ravel(),
                "box_centre": logit((np.asarray(centre, dtype=np.float64).reshape(-1, 3) - clo) / (chi - clo)).ravel(),
                "box_yaw": np.stack([np.cos(yaw), np.sin(yaw)], axis=1).ravel(),
                VELOCITY_LATENT: np.asarray(velocity, dtype=np.float64).ravel()}



@dataclass(frozen=True)
class CornerRange:
    """The fitted plan-corner cut of each car (metres, :class:`~vsrd_mi.optimise.config.CarProfile`):
    starts at ``start`` and stays within ``[0, max]``.

    The latent is scaled by ``gain`` inside the sigmoid so that an Adam step moves the cut about as
    far as it moves a half length (whose latent spans 2.5 m: ``2.5 * 0.25`` m per unit at the
    sigmoid's centre, against ``max * 0.25 * gain``); without it the cut would cross its range in
    several times the steps a box needs to settle.
    """

    start: float
    max: float
    gain: float = 4.0

    def __post_init__(self) -> None:
        if not 0.0 < self.start < self.max:
            raise ValueError(f"CornerRange: need 0 < start < max, got start={self.start}, max={self.max}")
        if self.gain <= 0:
            raise ValueError(f"CornerRange: gain must be > 0, got {self.gain}")

    @staticmethod
    def of_profile(profile: CarProfile) -> "CornerRange | None":
        """The range of the cut fitted under ``profile`` (``corner`` to ``corner_max``); None
        where it is not fitted (``fit_corner`` off, no cut, or the box corners projected)."""
        if profile.enabled and profile.fit_corner and profile.corner > 0:
            return CornerRange(profile.corner, profile.corner_max)
        return None

    def encode(self, count: int) -> np.ndarray:
        """The latents of ``count`` cuts at ``start``."""
        return np.full(count, logit(np.array(self.start / self.max)) / self.gain)


class BoxLatents:
    """Decodes the latents of ``count`` boxes within ``ranges`` (the range arrays built once),
    and of their plan-corner cuts within ``corner`` where given."""

    #: The range arrays, inputs of a frozen function that takes this object.
    DRJIT_STRUCT = {"span": list, "low": list}

    def __init__(self, ranges: BoxRanges, count: int, corner: CornerRange | None = None):
        self.ranges, self.count, self.corner = ranges, count, corner
        self.span = [to_float(np.tile(np.array(hi) - np.array(lo), count)) for lo, hi in
                     ((ranges.half_lo, ranges.half_hi), (ranges.centre_lo, ranges.centre_hi))]
        self.low = [to_float(np.tile(np.array(lo), count)) for lo in (ranges.half_lo, ranges.centre_lo)]

    def initial(self, centre: np.ndarray, size: np.ndarray, yaw: np.ndarray, velocity: np.ndarray) -> dict[str, mi.Float]:
        """Latent values of the given boxes (:meth:`BoxRanges.encode`, and the cuts'
        :meth:`CornerRange.encode` where fitted) as Dr.Jit arrays."""
        values = self.ranges.encode(centre, size, yaw, velocity)
        if self.corner is not None:
            values[CORNER_LATENT] = self.corner.encode(self.count)
        return {k: to_float(v) for k, v in values.items()}

    @property
    def box_keys(self) -> tuple[str, ...]:
        """The latents the box Adam holds: :data:`BOX_LATENTS` and the cut where fitted."""
        return BOX_LATENTS + ((CORNER_LATENT,) if self.corner is not None else ())

    def decode(self, latents: Mapping[str, mi.Float]) -> dict[str, mi.Float]:
        """The physical parameters ``centre``, ``size``, ``yaw`` (and ``velocity`` and the cut
        ``corner`` where their latents are given), differentiable w.r.t. the latents."""
        half = self.low[0] + self.span[0] * sigmoid(latents["box_dims"])
        pair = dr.arange(mi.UInt32, self.count) * 2
        yc, ys = dr.gather(mi.Float, latents["box_yaw"], pair), dr.gather(mi.Float, latents["box_yaw"], pair + 1)
        ok = yc * yc + ys * ys > YAW_PAIR_MIN_SQUARED
        out = {"centre": self.low[1] + self.span[1] * sigmoid(latents["box_centre"]), "size": 2.0 * half,
               "yaw": dr.atan2(dr.select(ok, ys, 0.0), dr.select(ok, yc, 1.0))}
        if VELOCITY_LATENT in latents:
            out["velocity"] = mi.Float(latents[VELOCITY_LATENT])
        if CORNER_LATENT in latents and self.corner is not None:
            out["corner"] = self.corner.max * sigmoid(self.corner.gain * latents[CORNER_LATENT])
        return out
