r"""Instance-aware NeuS silhouette integrator (``vsrd_silhouette``): soft instance labels of boxes
(plus an optional learned residual shape per box) along camera rays, differentiable w.r.t. the
boxes.

.. pluginparameters::

 * - centre
   - |string| or floats
   - Box centres in the scene frame, 3 numbers per box (scene units, e.g. m). The number of
     boxes ``N`` is their count / 3; without ``centre`` the scene has no boxes.
 * - size
   - |string| or floats
   - Full box extents (width, height, length) along the box-local x, y, z axes, 3 numbers per
     box, each > 0 (scene units). Required with ``centre``.
 * - yaw
   - |string| or floats
   - Rotation of each box about the scene's +y axis (radians); a box's length axis points along
     ``(sin yaw, 0, cos yaw)``. (Default: 0)
 * - velocity
   - |string| or floats
   - Velocity of each box, 3 numbers per box (scene units per unit of ray time: per frame when
     the sensors' ray time is the frame offset). (Default: 0)
 * - dynamic
   - |string| or floats
   - Per box 1 (moves: its centre at ray time ``t`` is ``centre + velocity * t``) or 0 (static).
     (Default: 0)
 * - residual
   - |bool|
   - Add the learned residual distance field (a hypernetwork MLP per box, bounded by 1 scene
     unit, inside each box) to every box SDF. (Default: false)
 * - residual_seed
   - |int|
   - Seed of the residual field's initial weights. (Default: 0)
 * - sampling
   - |string|
   - ``adaptive`` (bands of samples around each box a ray meets) or ``dense`` (the paper's
     stratified + importance samples over ``[near, far]``, a slow reference). (Default: adaptive)
 * - band_samples
   - |int|
   - Samples per band of the adaptive sampler, >= 2. (Default: 16)
 * - sharpness
   - |float|
   - NeuS sharpness ``s`` (1 / scene unit), > 0: labels blur over about ``1/s``. (Default: 10)
 * - temperature
   - |float|
   - Softmin temperature ``tau`` (scene units), > 0, between the labels of boxes that meet.
     (Default: 0.1)
 * - near
   - |float|
   - Start of the integration range along each ray (scene units), >= 0. (Default: 0)
 * - far
   - |float|
   - End of the integration range, > ``near``. (Default: 100)

List-valued properties are strings of numbers (space- or comma-separated, as XML has them),
Dr.Jit arrays (``mi.Float(values)``, ``mi.TensorXf(array)``) or, in ``mi.load_dict``, a tuple
of three numbers for one box's centre or size. Mitsuba's dictionary parser refuses other Python
lists and NumPy arrays before a plugin sees them: :func:`vsrd_plugins.box_properties` turns
them into strings. A value of the wrong type, count or range raises a
:class:`~vsrd_plugins.properties.PropertyError` naming the property.

``mi.traverse(scene)`` lists, for an integrator with ``id="vsrd"``: ``vsrd.centre``,
``vsrd.size``, ``vsrd.yaw``, ``vsrd.velocity`` (differentiable, the units above),
``vsrd.dynamic``, ``vsrd.sharpness`` and ``vsrd.temperature`` (opaque: changing them every step
compiles nothing anew) and, with the residual field only, its embedding and hypernetwork
weights ``vsrd.rdf_*``. :meth:`VSRDSilhouetteIntegrator.boxes` reads the boxes back as NumPy.
Internal tuning (band reach, residual search, isolated rays, ...) is a
:class:`~vsrd_plugins.silhouette.settings.SilhouetteSettings` on ``integrator.settings``.

``mi.render`` returns ``3 + N + 1`` channels per pixel: RGB (each box's colour,
:func:`~vsrd_plugins.common.instance_colours`, weighted by its label), then the AOVs
``label_0`` ... ``label_{N-1}`` (the soft label of each box, in box order) and ``background``
(``1 - sum`` of the labels). :meth:`VSRDSilhouetteIntegrator.render_rays` renders any batch of
rays (one launch for many cameras) and returns the ``N + 1`` labels.

.. code-block:: python

    import drjit as dr, mitsuba as mi, numpy as np
    mi.set_variant("llvm_ad_rgb")
    import vsrd_plugins
    vsrd_plugins.register()
    scene = mi.load_dict({"type": "scene",
        "sensor": {"type": "perspective", "fov": 60, "film": {"type": "hdrfilm", "width": 64, "height": 48}},
        "integrator": {"type": "vsrd_silhouette", "id": "vsrd",
                       **vsrd_plugins.box_properties(centre=[[0, 0, 8]], size=[[1.8, 1.5, 4.2]], yaw=[0.3])}})
    image = mi.render(scene, spp=1)                # (48, 64, 3 + 1 + 1): RGB, label_0, background
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=0.02, params={"vsrd.centre": params["vsrd.centre"]})

The integral, both samplers and the residual search: ``docs/integrators.md``.
"""

from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..common import instance_colours
from ..properties import PropertyError, read_float
from ..sdf import InstanceField
from .adaptive import render_adaptive
from .dense import integrate_at, render_dense
from .settings import PLUGIN, SamplingContext, SilhouetteSettings

#: Default NeuS sharpness ``s`` (1 / scene unit) and softmin temperature ``tau`` (scene units).
DEFAULT_SHARPNESS, DEFAULT_TEMPERATURE = 10.0, 0.1

__all__ = ["VSRDSilhouetteIntegrator", "SilhouetteSettings", "instance_colours"]


class VSRDSilhouetteIntegrator(mi.ad.integrators.common.ADIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.field = InstanceField(props, PLUGIN)
        self._settings = SilhouetteSettings.from_props(props)
        self.sharpness = dr.opaque(mi.Float, read_float(props, PLUGIN, "sharpness", DEFAULT_SHARPNESS, positive=True))
        self.temperature = dr.opaque(mi.Float, read_float(props, PLUGIN, "temperature", DEFAULT_TEMPERATURE,
                                                          positive=True))
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
        """Check the widths of the box parameters and keep ``s`` and ``tau`` opaque."""
        self.field.check_parameters()
        for k in ("sharpness", "temperature"):
            v = getattr(self, k)
            if dr.width(v) != 1:
                raise PropertyError(f"{PLUGIN}: parameter '{k}' must be a single value, got {dr.width(v)}")
            dr.make_opaque(v)

    def boxes(self) -> dict[str, np.ndarray]:
        """The boxes as NumPy arrays: ``centre`` (N, 3), ``size`` (N, 3), ``yaw`` (N,),
        ``velocity`` (N, 3) and ``dynamic`` (N,), in the units of the plugin properties."""
        return self.field.boxes()

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
