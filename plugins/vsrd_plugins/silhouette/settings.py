"""Settings of ``vsrd_silhouette`` and the context one call of its samplers runs in.

:class:`SilhouetteSettings` holds every sampling setting: the few that are plugin properties
(``sampling``, ``band_samples``, ``near``, ``far``) and the internal tuning, whose defaults were
measured (``docs/integrators.md``, "What each feature buys"). Change them from Python::

    from dataclasses import replace
    integrator.settings = replace(integrator.settings, residual_tail=0)

:class:`SamplingContext` bundles what the sampler modules read during one call: the instance
field, the settings, the schedule values ``s`` and ``tau`` and the quantities derived from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import drjit as dr
import mitsuba as mi

from ..properties import PropertyError, read_choice, read_float, read_int
from ..sdf import InstanceField

PLUGIN = "vsrd_silhouette"
SAMPLINGS = ("adaptive", "dense")
RESIDUAL_GRADIENTS = ("fused", "tensor")


@dataclass(frozen=True)
class SilhouetteSettings:
    """Sampling settings of ``vsrd_silhouette`` (see the module docstring)."""

    #: ``adaptive`` (bands around each box a ray meets) or ``dense`` (the paper's stratified +
    #: importance samples over ``[near, far]``, a reference). Plugin property.
    sampling: str = "adaptive"
    #: ``K``: samples per band of the adaptive sampler. Plugin property.
    band_samples: int = 16
    #: Integration range along each ray (scene units). Plugin properties.
    near: float = 0.0
    far: float = 100.0
    #: Dense sampling: stratified coarse and importance-sampled fine samples per ray (the paper's).
    coarse_samples: int = 100
    fine_samples: int = 100
    #: Band half-width ``reach / s`` and culling margin ``reach * max(1/s, tau)``: beyond the
    #: margin a box's opacity and softmin share are below ``exp(-reach)``.
    reach: float = 8.0
    #: At most this many bands (nearest deepest point first) per ray; 0: one per box it meets.
    max_bands: int = 0
    #: Golden-section steps of the detached searches on the convex box SDF (closest approach,
    #: gap peaks).
    golden_iterations: int = 24
    #: Each ray's deepest sample inside a box (and the gap peaks and kink minima) carries the
    #: envelope gradient instead of AD's one-sided gradient of the max over faces.
    ridge_gradients: bool = True
    #: Rays whose enlarged boxes are disjoint along them ("isolated") get a layout of their own:
    #: ``isolated_band_samples`` band samples per box without the residual field; with it the
    #: bands' anchors and the extrema of ``B + R``, where each band has at most
    #: ``isolated_extrema`` of them and the batch's isolated rays save more samples than their
    #: sample groups cost (``isolated_group_cost`` samples each: a group's kernel launches and
    #: tracing, about 2.5 ms).
    isolated_rays: bool = True
    isolated_band_samples: int = 1
    isolated_extrema: int = 3
    isolated_group_cost: int = 25000
    #: With the residual field: points scanned per band for the least ``B + R`` (0: the band
    #: sits at the box's own minimum, no tails, no moved samples, no chord grid).
    residual_scan: int = 4
    #: With the residual search: tail samples per band covering the rest of the enlarged box's
    #: chord, where ``B + R`` can dip again.
    residual_tail: int = 12
    #: With the tail samples: detached scan points per band or tail sample; every local extremum
    #: of ``B + R`` the scan finds claims a sample (0: samples stay at their nominal places).
    residual_tail_scan: int = 3
    #: With the residual search: the scans read ``R`` interpolated from exact values on a grid
    #: along each band's chord, spaced this many radians of the encoding's highest frequency
    #: (0: ``R`` evaluated at every scan point).
    residual_grid: float = 0.35
    #: With the chord grid: tabulate ``R`` per instance on a box-local lattice this many radians
    #: apart where that costs fewer MLP evaluations than the grid's points (0: never).
    residual_lattice: float = 0.35
    #: How gradients reach the residual MLP: ``fused`` (hand-written derivatives around one
    #: cooperative-vector kernel, LLVM) or ``tensor`` (Dr.Jit AD through tensor-mode matmuls).
    residual_gradients: str = "fused"

    def validated(self) -> "SilhouetteSettings":
        """These settings, or a :class:`~vsrd_plugins.properties.PropertyError` naming the field
        whose value does not fit."""
        def bad(name: str, rule: str) -> PropertyError:
            return PropertyError(f"{PLUGIN}: setting '{name}' must be {rule}, got {getattr(self, name)!r}")

        if self.sampling not in SAMPLINGS:
            raise bad("sampling", f"one of {SAMPLINGS}")
        if self.residual_gradients not in RESIDUAL_GRADIENTS:
            raise bad("residual_gradients", f"one of {RESIDUAL_GRADIENTS}")
        minimum = {"band_samples": 2, "coarse_samples": 2, "fine_samples": 1, "max_bands": 0, "golden_iterations": 1,
                   "isolated_band_samples": 1, "isolated_extrema": 0, "isolated_group_cost": 0, "residual_scan": 0,
                   "residual_tail": 0, "residual_tail_scan": 0}
        for name, low in minimum.items():
            if getattr(self, name) < low:
                raise bad(name, f">= {low}")
        if self.residual_scan == 1:
            raise bad("residual_scan", "0 or >= 2 (a scan needs two points)")
        for name in ("reach", "residual_grid", "residual_lattice"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= (0.0 if name != "reach" else 1e-9)):
                raise bad(name, "finite and > 0" if name == "reach" else "finite and >= 0")
        if not (math.isfinite(self.near) and math.isfinite(self.far) and 0.0 <= self.near < self.far):
            raise PropertyError(f"{PLUGIN}: properties 'near' and 'far' need 0 <= near < far, "
                                f"got {self.near!r}, {self.far!r}")
        return self

    @staticmethod
    def from_props(props) -> "SilhouetteSettings":
        """The settings given as plugin properties (:data:`PROPERTIES`; the rest at their
        defaults). A setting given as a property raises an error that says how to set it."""
        d = SilhouetteSettings()
        for name in props.keys():
            if name in INTERNAL:
                raise PropertyError(f"{PLUGIN}: '{name}' is an internal setting, not a plugin property: set it "
                                    f"from Python, integrator.settings = dataclasses.replace(integrator.settings, "
                                    f"{name}=...)")
        return SilhouetteSettings(
            sampling=read_choice(props, PLUGIN, "sampling", d.sampling, SAMPLINGS),
            band_samples=read_int(props, PLUGIN, "band_samples", d.band_samples, 2),
            near=read_float(props, PLUGIN, "near", d.near, minimum=0.0),
            far=read_float(props, PLUGIN, "far", d.far, positive=True)).validated()


#: The settings that are plugin properties; the others (:data:`INTERNAL`) are set from Python.
PROPERTIES = ("sampling", "band_samples", "near", "far")
INTERNAL = tuple(f.name for f in fields(SilhouetteSettings) if f.name not in PROPERTIES)


def halves(kk: int) -> tuple[int, int]:
    """Band samples up to a band's centre (the last of them at it) and after it."""
    k1 = max(kk // 2, 1)
    return k1, kk - k1


@dataclass
class SamplingContext:
    """What one call of the samplers reads: the field, the settings and the schedule."""

    field: InstanceField
    settings: SilhouetteSettings
    sharpness: mi.Float  #: ``s`` (1/scene unit), opaque
    temperature: mi.Float  #: ``tau`` (scene units), opaque
    #: Rays, samples and (sample, instance) SDF evaluations of the call, for tests and benchmarks.
    stats: dict = field(default_factory=lambda: {"rays": 0, "samples": 0, "sdf_evals": 0})

    def count(self, rays: int, samples_per_ray: int, instances: int) -> None:
        """Add ``rays`` rays of ``samples_per_ray`` samples, ``instances`` evaluated at each."""
        for key, v in (("rays", rays), ("samples", rays * samples_per_ray),
                       ("sdf_evals", rays * samples_per_ray * instances)):
            self.stats[key] += v

    def band_half_width(self) -> mi.Float:
        """Band half-width ``reach / s`` in scene units."""
        return self.settings.reach / self.sharpness

    def cull_margin(self) -> mi.Float:
        """Box SDF value beyond which an instance is dropped from a ray: ``reach * max(1/s, tau)``.

        Past it both its opacity (``Phi_s``) and its softmin label share next to a surface are
        below ``exp(-reach)``."""
        return self.settings.reach * dr.maximum(1.0 / self.sharpness, self.temperature)

    def residual_reach(self) -> mi.Float:
        """Where the residual is evaluated: inside boxes enlarged by the culling margin (opaque:
        a literal would recompile whenever ``s`` changes). ``R >= 0``, so where the box SDF is
        beyond the margin ``B + R`` is too, and the residual cannot move the integral there by
        more than the culling bound."""
        return dr.detach(self.cull_margin())

    def residual_search(self) -> bool:
        """Whether bands are placed at the least ``B + R``: the residual field is on and
        ``residual_scan > 0``. The tail samples come with it."""
        return self.field.residual_reach > 0 and self.settings.residual_scan > 0

    def tail_samples(self) -> tuple[int, int]:
        """Tail samples per band before and after its minimum sample (``residual_tail`` split in
        two with the residual search, else none)."""
        kt = self.settings.residual_tail if self.residual_search() else 0
        return kt // 2, kt - kt // 2

    def snaps(self) -> bool:
        """Whether band and tail samples move to the extrema of ``B + R``: the tail samples are
        on and ``residual_tail_scan > 0``."""
        return self.tail_samples()[1] > 0 and self.settings.residual_tail_scan > 0

    def isolates(self) -> bool:
        """Whether isolated rays get their own layout: ``isolated_rays`` is on and either the
        residual field is off or its extrema are searched (moved samples and the chord grid on:
        ``B + R`` need not be convex along a ray, and the isolated layout samples its extrema)."""
        return self.settings.isolated_rays and (self.field.residual_reach == 0
                                                or (self.snaps() and self.settings.residual_grid > 0))

    def residual_omega(self) -> float:
        """The residual encoding's highest frequency in rad per scene unit: ``2^(F-1) pi`` times
        its input scale (4 rad/m by default)."""
        rcfg = self.field.residual.cfg
        return math.pi * 2.0 ** (rcfg.frequencies - 1) * rcfg.input_scale
