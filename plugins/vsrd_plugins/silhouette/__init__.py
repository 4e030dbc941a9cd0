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

The integral, both samplers and the residual search are described in ``docs/integrators.md``.
"""

from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi

from ..common import instance_colours
from ..sdf import InstanceField
from .adaptive import render_adaptive
from .dense import integrate_at, render_dense
from .settings import SamplingContext, SilhouetteSettings

__all__ = ["VSRDSilhouetteIntegrator", "SilhouetteSettings", "instance_colours"]


class VSRDSilhouetteIntegrator(mi.ad.integrators.common.ADIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.field = InstanceField(props)
        self._settings = SilhouetteSettings.from_props(props)
        self.sharpness = dr.opaque(mi.Float, float(props.get("sharpness", 10.0)))
        self.temperature = dr.opaque(mi.Float, float(props.get("temperature", 0.1)))
        #: Rays, samples and (sample, instance) SDF evaluations of the last call.
        self.last_stats: dict[str, int] = {}

    @property
    def settings(self) -> SilhouetteSettings:
        """The sampling settings (:class:`SilhouetteSettings`); assign a changed copy
        (``dataclasses.replace``) to change them."""
        return self._settings

    @settings.setter
    def settings(self, value: SilhouetteSettings) -> None:
        self._settings = value.validated()
        if self.field.residual is not None:
            self.field.residual.cfg = replace(self.field.residual.cfg, gradients=value.residual_gradients)

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
        return (f"VSRDSilhouetteIntegrator[instances={self.field.n}, sampling={self.settings.sampling}, "
                f"residual={self.field.use_residual}]")

    def sample(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True, **kwargs):
        labels = self.render_rays(mi.Point3f(ray.o), mi.Vector3f(ray.d), mi.Float(ray.time))
        colours = instance_colours(self.field.n)
        rgb = mi.Color3f(0.0)
        for lab, c in zip(labels[:-1], colours):
            rgb += mi.Color3f(*c) * lab
        return mi.Spectrum(rgb), mi.Bool(active), labels, None

    # -- the integral --------------------------------------------------------------------------
    def context(self) -> SamplingContext:
        """The sampling context of a call with the current boxes, settings and schedule."""
        return SamplingContext(self.field, self.settings, self.sharpness, self.temperature)

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
        ctx = self.context()
        self.last_stats = ctx.stats
        if self.settings.sampling == "dense":
            labels = render_dense(ctx, dec, o, d, time)
        else:
            labels = render_adaptive(ctx, dec, o, d, time)
        if labels is None:  # no ray meets any (enlarged) box
            return [dr.zeros(mi.Float, n_rays) for _ in range(self.field.n)] + [dr.ones(mi.Float, n_rays)]
        total = labels[0]
        for lab in labels[1:]:
            total = total + lab
        return labels + [1.0 - total]

    def integrate_at(self, dec, ray_idx: mi.UInt32, o, d, time, t: mi.Float, m: int) -> list[mi.Float]:
        """Labels of rays ``ray_idx`` from the NeuS integral at given sorted samples ``t`` (``m``
        per ray), the integral both samplers use: for references and tests."""
        return integrate_at(self.context(), dec, ray_idx, o, d, time, t, m)
