r"""Sphere-traced instance id, depth and normal of the boxes (``sdf_tracer``).

.. pluginparameters::

 * - centre, size, yaw, velocity, dynamic
   - |string| or floats
   - The boxes, as for ``vsrd_silhouette`` (one row each there): centres and full sizes (3 per
     box, scene units), yaws (radians), velocities (per unit of ray time) and 0/1 dynamic
     flags. Ray time moves dynamic boxes: ``centre(t) = centre + velocity * t``.
 * - residual
   - |bool|
   - Add the residual distance field to every box SDF. (Default: false)
 * - residual_seed
   - |int|
   - Seed of the residual field's initial weights. (Default: 0)
 * - max_iterations
   - |int|
   - Sphere-tracing iterations per ray, >= 1; rays still marching after them are background.
     (Default: 256)
 * - epsilon
   - |float|
   - Hit tolerance (scene units), > 0: a ray whose scene SDF drops below it has hit.
     (Default: 1e-5)
 * - near
   - |float|
   - Start of the tracing range along each (normalised) ray direction, >= 0. (Default: 0)
 * - far
   - |float|
   - End of the tracing range, > ``near``. (Default: 200)

The internal settings (start margin, root refinement, normal step) are a
:class:`TracerSettings` on ``integrator.settings``.

Every box parameter (``tracer.centre``, ``tracer.size``, ...) and, with the residual field,
its weights (``tracer.rdf_*``) appear in ``mi.traverse(scene)`` when the integrator has
``id="tracer"``, under the same names as ``vsrd_silhouette``'s, so an optimised parameter set
can be copied over. Nothing here is differentiable: the tracer is for inspection (instance maps, depth,
normals), not for optimisation.

Algorithm
---------

The scene SDF is ``F(p) = min_n F_n(p)`` at the ray's time (:mod:`vsrd_plugins.sdf`). Per ray:

1. *Start.* A slab test against every instance's box enlarged by ``start_margin`` plus the
   residual's reach (:attr:`InstanceField.residual_reach`) gives intervals ``[a_n, b_n]``; the
   ray starts at ``min_n a_n`` (outside every surface); a ray that meets no enlarged box is
   background at once.
2. *March* (a Python-level wavefront loop; the residual MLP runs in Dr.Jit tensor mode, which
   cannot run inside ``dr.while_loop``). Each iteration evaluates ``f = F(o + t d)`` on the
   rays still marching and compacts the others away (``dr.compress``):

   * ``f < 0``: the step crossed the surface; ``[t_prev, t]`` brackets it;
   * ``0 <= f < epsilon``: hit at ``t`` (no bracket: a ray passing within ``epsilon`` of a surface);
   * otherwise step by the largest distance over which ``F`` provably stays positive: per
     instance, the box SDF ``B_n`` is convex along the ray and ``F_n >= B_n``, so outside the
     box the tangent-line (Newton) step ``B_n / -g_n`` (``g_n = dB_n/dt < 0``) is safe and no
     bound is needed when ``g_n >= 0``; inside the box (residual surface) the sphere step
     ``F_n``. The step is the minimum over instances (:meth:`SDFTracerIntegrator._safe_step`).
     Plain sphere tracing needs ``~log(f/epsilon) / sin(theta)`` iterations for a ray at angle
     ``theta`` to a face and ``~L / h`` for a ray running parallel to a face at distance ``h``;
     the tangent step reaches a face in one step and jumps past near misses;
   * a step that leaves every enlarged box jumps to the next enlarged-box entry along the ray,
     or ends the ray as background when there is none or it passes ``far``.
3. *Refine.* Bracketed hits are refined by the Illinois variant of regula falsi until the
   bracket is narrower than ``depth_tolerance``; the depth is the final secant root.
4. *Shade.* The hit instance is ``argmin_n F_n`` at the hit; its normal is the box normal
   (:func:`box_normal_local`) for boxes, or central finite differences of ``F_n`` when the
   residual is on.

Box SDFs are evaluated in double precision: a single-precision point 80 m away carries
``~5e-6`` m of rounding, which a ray at grazing angle ``theta`` turns into ``5e-6 / sin(theta)``
of depth error. (Box centres at the ray time are computed by :meth:`InstanceField.view` in
single precision; the residual MLP runs in single precision.)

For ``F = B + R`` the sphere steps inside a box assume the residual keeps ``F`` 1-Lipschitz
along rays; if it does not, a step may end inside the surface, which step 2 detects as a
bracket. A ray whose origin lies inside a surface hits it at ``t = near``.

Output (:meth:`SDFTracerIntegrator.trace_rays`): ``hit`` (Bool), ``instance`` (Int, -1 for
background), ``t`` (distance along the normalised direction, 0 for background), ``depth``
(camera z of the hit when a sensor is given, else ``t``), ``normal`` (unit, scene frame, 0 for
background). :meth:`sample` (``mi.render``) returns the instance colour
(:func:`vsrd_plugins.silhouette.instance_colours`) shaded by ``|n . d|`` on black and the AOVs
``instance, depth, nx, ny, nz`` (render with ``spp=1`` and a ``box`` filter so that the AOVs are
not averaged across pixels).

Usage
-----

.. code-block:: python

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import vsrd_plugins
    vsrd_plugins.register()
    scene = mi.load_dict({'type': 'scene',
        'sensor': {'type': 'perspective', 'film': {'type': 'hdrfilm', 'rfilter': {'type': 'box'}}},
        'integrator': {'type': 'sdf_tracer', 'id': 'tracer',
                       **vsrd_plugins.box_properties(centre=[[0, 0, 8]], size=[[1.8, 1.5, 4.2]], yaw=[0.3])}})
    image = mi.render(scene, spp=1)           # RGB + instance, depth, nx, ny, nz
    out = scene.integrator().trace_rays(origins, directions, times)
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .common import instance_colours
from .properties import PropertyError, read_float, read_int
from .sdf import BoxView, DecodedBoxes, InstanceField, box_normal_local, box_sdf_local, ray_box_interval

INF = float("inf")
PLUGIN = "sdf_tracer"


@dataclass(frozen=True)
class TracerSettings:
    """Settings of :class:`SDFTracerIntegrator` (the first four are plugin properties)."""

    max_iterations: int = 256
    epsilon: float = 1e-5  #: hit tolerance of the march (scene units)
    near: float = 0.0
    far: float = 200.0  #: beyond a box 110 m away plus a vehicle
    start_margin: float = 0.05  #: enlargement of the start boxes (the march starts strictly outside)
    refine_iterations: int = 64  #: at most this many Illinois steps of the root refinement
    depth_tolerance: float = 1e-6  #: final bracket width of the refinement (scene units)
    normal_step: float = 1e-3  #: central finite-difference step of residual normals (scene units)

    def validated(self) -> "TracerSettings":
        """These settings, or a :class:`~vsrd_plugins.properties.PropertyError` naming the field
        whose value does not fit."""
        for name in ("max_iterations", "refine_iterations"):
            if getattr(self, name) < (1 if name == "max_iterations" else 0):
                raise PropertyError(f"{PLUGIN}: '{name}' must be >= {1 if name == 'max_iterations' else 0}, "
                                    f"got {getattr(self, name)}")
        for name in ("epsilon", "depth_tolerance", "normal_step"):
            if not getattr(self, name) > 0:
                raise PropertyError(f"{PLUGIN}: '{name}' must be > 0, got {getattr(self, name)}")
        if not self.start_margin >= 0:
            raise PropertyError(f"{PLUGIN}: 'start_margin' must be >= 0, got {self.start_margin}")
        if not (0.0 <= self.near < self.far):
            raise PropertyError(f"{PLUGIN}: properties 'near' and 'far' need 0 <= near < far, got {self.near}, {self.far}")
        return self

    @staticmethod
    def from_props(props) -> "TracerSettings":
        d = TracerSettings()
        return TracerSettings(max_iterations=read_int(props, PLUGIN, "max_iterations", d.max_iterations, 1),
                              epsilon=read_float(props, PLUGIN, "epsilon", d.epsilon, positive=True),
                              near=read_float(props, PLUGIN, "near", d.near, minimum=0.0),
                              far=read_float(props, PLUGIN, "far", d.far, positive=True)).validated()


def _to_local64(bv: BoxView, p: mi.Point3d) -> mi.Vector3d:
    """Box-local coordinates ``R_y^T (p - centre)`` in double precision.

    Same transform as :meth:`BoxView.to_local`, which rounds its result to single precision.
    """
    c, s = mi.Float64(bv.cos), mi.Float64(bv.sin)
    v = p - mi.Point3d(bv.centre)
    return mi.Vector3d(c * v.x - s * v.z, v.y, s * v.x + c * v.z)


class SDFTracerIntegrator(mi.ad.integrators.common.ADIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.field = InstanceField(props, PLUGIN)
        #: The tracer's settings (:class:`TracerSettings`); assign a changed copy to change them.
        self.settings = TracerSettings.from_props(props)
        self._sensor: mi.Sensor | None = None
        #: Counters of the last :meth:`trace_rays` call (for benchmarks and tests).
        self.last_stats: dict[str, int] = {}

    # -- Mitsuba plumbing ----------------------------------------------------------------------
    def traverse(self, cb: mi.TraversalCallback) -> None:
        self.field.traverse(cb)

    def parameters_changed(self, keys: list[str]) -> None:
        """Check the widths of the box parameters (nothing is cached: they are read at every call)."""
        self.field.check_parameters()

    def boxes(self) -> dict:
        """The boxes as NumPy arrays (:meth:`~vsrd_plugins.sdf.InstanceField.boxes`)."""
        return self.field.boxes()

    def aov_names(self) -> list[str]:
        return ["instance", "depth", "nx", "ny", "nz"]

    def to_string(self) -> str:
        return (f"SDFTracerIntegrator[instances={self.field.n}, residual={self.field.use_residual}, "
                f"max_iterations={self.settings.max_iterations}, epsilon={self.settings.epsilon}]")

    def render(self, scene: mi.Scene, sensor=0, seed=0, spp: int = 0, develop: bool = True,
               evaluate: bool = True) -> mi.TensorXf:
        """``mi.render`` entry point; remembers the sensor so :meth:`sample` can report camera z."""
        self._sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        try:
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        finally:
            self._sensor = None

    def sample(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True, **kwargs):
        out = self.trace_rays(mi.Point3f(ray.o), mi.Vector3f(ray.d), mi.Float(ray.time), self._sensor)
        n_rays = dr.width(out["t"])
        d = dr.normalize(mi.Vector3f(ray.d))
        shade = dr.abs(dr.dot(out["normal"], d))
        rgb = mi.Color3f(0.0)
        for k, c in enumerate(instance_colours(self.field.n)):
            rgb = dr.select(out["instance"] == k, mi.Color3f(*c) * shade, rgb)
        n = out["normal"]
        aovs = [mi.Float(out["instance"]), out["depth"], n.x, n.y, n.z]
        aovs = [a if dr.width(a) == n_rays else dr.full(mi.Float, a[0], n_rays) for a in aovs]
        return mi.Spectrum(rgb), mi.Bool(active), aovs, None

    # -- fields in double precision --------------------------------------------------------------
    def _instance_sdf(self, dec: DecodedBoxes, weights, k: int, p: mi.Point3d,
                      time: mi.Float) -> mi.Float64:
        """``F_k(p)`` (box SDF in double precision, plus the residual where it can act)."""
        width = dr.width(p.x)
        bv = self.field.view(dec, k, time, width)
        pl = _to_local64(bv, p)
        f = box_sdf_local(pl, mi.Vector3d(bv.half))
        if weights is not None:
            f = f + self._residual(weights, k, pl, bv.half)
        return f

    def _residual(self, weights, k: int, pl: mi.Vector3d, half: mi.Vector3f) -> mi.Float64:
        """Residual of instance ``k`` inside its box enlarged by the residual's reach, else 0.

        Outside that box ``B_k >= reach >= R_k`` and leaving the residual out keeps ``F_k`` a lower
        bound there, which is what the march needs (the same culling as
        :meth:`InstanceField.instance_sdfs`).
        """
        width = dr.width(pl.x)
        reach = self.field.residual_reach
        inside = dr.all(dr.abs(pl) <= mi.Vector3d(half) + reach)
        idx = dr.compress(inside)
        out = dr.zeros(mi.Float64, width)
        if dr.width(idx) > 0:
            pk = mi.Vector3f(*[mi.Float(dr.gather(mi.Float64, c, idx)) for c in (pl.x, pl.y, pl.z)])
            r = self.field.residual.evaluate(weights, k, pk)
            dr.scatter(out, mi.Float64(r), idx)
        return out

    def _scene_sdf(self, dec, weights, p: mi.Point3d, time: mi.Float) -> tuple[mi.Float64, mi.Int32]:
        """Scene SDF ``min_k F_k(p)`` and the index of the minimising instance."""
        best = dr.full(mi.Float64, INF, dr.width(p.x))
        arg = dr.full(mi.Int32, -1, dr.width(p.x))
        for k in range(self.field.n):
            f = self._instance_sdf(dec, weights, k, p, time)
            closer = f < best
            best = dr.select(closer, f, best)
            arg = dr.select(closer, k, arg)
        return best, arg

    def _safe_step(self, dec, weights, p: mi.Point3d, d: mi.Vector3d,
                   time: mi.Float) -> tuple[mi.Float64, mi.Float64]:
        """Scene SDF ``f`` at ``p`` and a step along ``d`` over which ``F`` stays positive.

        Per instance, a box SDF is convex along a ray, so it lies above its tangent line:
        ``B_k(t + s) >= B_k + g_k s`` with ``g_k = dB_k/dt``, and ``F_k >= B_k`` (the residual
        is >= 0). Outside the box the step ``B_k / -g_k`` (``g_k < 0``) or no bound at all
        (``g_k >= 0``: the ray moves away from the box for good) is therefore safe, and never
        shorter than the sphere step ``F_k`` without the residual; inside the box (the residual
        surface lies within) the sphere step ``F_k`` is used. The step is the minimum over
        instances (``inf``: nothing ahead can be hit).
        """
        width = dr.width(p.x)
        f = dr.full(mi.Float64, INF, width)
        step = dr.full(mi.Float64, INF, width)
        for k in range(self.field.n):
            bv = self.field.view(dec, k, time, width)
            pl = _to_local64(bv, p)
            b = box_sdf_local(pl, mi.Vector3d(bv.half))
            fk = b if weights is None else b + self._residual(weights, k, pl, bv.half)
            nl = box_normal_local(mi.Vector3f(pl), bv.half)
            g = mi.Float64(dr.dot(bv.dir_to_local(mi.Vector3f(d)), nl))
            tangent = dr.select(g < 0, b / dr.maximum(-g, 1e-300), INF)
            sk = dr.select(b > 0, dr.maximum(fk, tangent), fk)
            f = dr.minimum(f, fk)
            step = dr.minimum(step, sk)
        return f, step

    # -- the tracer ----------------------------------------------------------------------------
    def trace_rays(self, o: mi.Point3f, d: mi.Vector3f, time: mi.Float,
                   sensor: mi.Sensor | None = None) -> dict[str, object]:
        """Trace a batch of rays (any cameras, per-ray frame offset ``time``); no gradients.

        ``d`` need not be normalised; ``t`` is the distance along it. With ``sensor``, ``depth``
        is the hit's z in that sensor's camera frame (its optical axis from its world transform),
        otherwise ``depth = t``. Returns ``hit`` (Bool), ``instance`` (Int, -1 for background),
        ``t``, ``depth`` (Float, 0 for background) and ``normal`` (unit Vector3f, 0 for background).
        """
        with dr.suspend_grad():
            n_rays = max(dr.width(o.x), dr.width(d.x), dr.width(time))
            o64 = mi.Point3d(mi.Point3d(o) + dr.zeros(mi.Vector3d, n_rays))
            d64 = mi.Vector3d(dr.normalize(mi.Vector3d(d)) + dr.zeros(mi.Vector3d, n_rays))
            time = dr.detach(mi.Float(time)) + dr.zeros(mi.Float, n_rays)
            status, ta, tb, fa, fb = self._march(o64, d64, time)
            t = self._refine(o64, d64, time, status, ta, tb, fa, fb)
            hit = status > 0
            instance, normal = self._shade(o64, d64, time, t, hit)
            t = dr.select(hit, t, 0.0)
            if sensor is not None:
                to_world = sensor.world_transform()
                axis = mi.Vector3d(dr.normalize(to_world @ mi.Vector3f(0.0, 0.0, 1.0)))
                origin = mi.Point3d(to_world @ mi.Point3f(0.0, 0.0, 0.0))
                depth = dr.select(hit, dr.dot(o64 + t * d64 - origin, axis), 0.0)
            else:
                depth = t
            return {"hit": hit, "instance": instance, "t": mi.Float(t), "depth": mi.Float(depth),
                    "normal": normal}

    def _march(self, o: mi.Point3d, d: mi.Vector3d, time: mi.Float):
        """Steps 1-2 of the algorithm. Returns full-width ``(status, ta, tb, fa, fb)``.

        ``status``: 0 background, 1 hit at ``ta`` (no bracket), 2 surface bracketed by
        ``[ta, tb]`` with ``fa > 0 > fb``.
        """
        cfg, n_inst = self.settings, self.field.n
        n = dr.width(o.x)
        status = dr.zeros(mi.UInt32, n)
        ta, tb, fa, fb = (dr.zeros(mi.Float64, n) for _ in range(4))
        self.last_stats = {"rays": n, "marching": 0, "iterations": 0, "unconverged": 0,
                           "refine_unconverged": 0}
        if n_inst == 0:
            return status, ta, tb, fa, fb
        dec = self.field.decode()
        weights = self.field.residual_weights()
        margin = cfg.start_margin + self.field.residual_reach
        entry, exit_ = [], []
        o32, d32 = mi.Point3f(o), mi.Vector3f(d)
        for k in range(n_inst):
            bv = self.field.view(dec, k, time, n)
            a, b = ray_box_interval(bv.to_local(o32), bv.dir_to_local(d32), bv.half + margin)
            a, b = mi.Float64(dr.maximum(a, cfg.near)), mi.Float64(dr.minimum(b, cfg.far))
            ok = a <= b
            entry.append(dr.select(ok, a, INF))
            exit_.append(dr.select(ok, b, -INF))
        start = entry[0]
        for a in entry[1:]:
            start = dr.minimum(start, a)
        ridx = dr.compress(start < INF)
        t = dr.gather(mi.Float64, start, ridx)
        t_prev = dr.zeros(mi.Float64, dr.width(ridx))
        f_prev = dr.full(mi.Float64, INF, dr.width(ridx))
        self.last_stats["marching"] = dr.width(ridx)
        for it in range(cfg.max_iterations):
            m = dr.width(ridx)
            if m == 0:
                break
            self.last_stats["iterations"] = it + 1
            og, dg = dr.gather(mi.Point3d, o, ridx), dr.gather(mi.Vector3d, d, ridx)
            f, step = self._safe_step(dec, weights, mi.Point3d(og + t * dg), dg,
                                      dr.gather(mi.Float, time, ridx))
            has_prev = f_prev < INF
            crossed = (f < 0) & has_prev
            stop = (f < cfg.epsilon) & ~crossed  # converged, or started inside a surface
            dr.scatter(status, 2, ridx, crossed)
            dr.scatter(ta, t_prev, ridx, crossed)
            dr.scatter(fa, f_prev, ridx, crossed)
            dr.scatter(tb, t, ridx, crossed)
            dr.scatter(fb, f, ridx, crossed)
            dr.scatter(status, 1, ridx, stop)
            dr.scatter(ta, t, ridx, stop)
            dr.scatter(fa, f, ridx, stop)
            t_next = t + step
            inside = mi.Bool(False)
            next_entry = dr.full(mi.Float64, INF, m)
            for k in range(n_inst):
                a, b = dr.gather(mi.Float64, entry[k], ridx), dr.gather(mi.Float64, exit_[k], ridx)
                inside |= (a <= t_next) & (t_next <= b)
                next_entry = dr.minimum(next_entry, dr.select(a > t_next, a, INF))
            jump = ~inside
            t_next = dr.select(jump, next_entry, t_next)
            alive = ~crossed & ~stop & (t_next <= cfg.far)
            keep = dr.compress(alive)
            ridx = dr.gather(mi.UInt32, ridx, keep)
            t_prev = dr.gather(mi.Float64, t, keep)
            f_prev = dr.gather(mi.Float64, dr.select(jump, INF, f), keep)
            t = dr.gather(mi.Float64, t_next, keep)
        self.last_stats["unconverged"] = dr.width(ridx) if self.last_stats["iterations"] == cfg.max_iterations else 0
        return status, ta, tb, fa, fb

    def _refine(self, o, d, time, status, ta, tb, fa, fb) -> mi.Float64:
        """Step 3: Illinois regula falsi on bracketed rays. Returns the full-width ``t``."""
        cfg = self.settings
        t_out = mi.Float64(ta)
        ridx = dr.compress(status == 2)
        if dr.width(ridx) == 0:
            return t_out
        dec = self.field.decode()
        weights = self.field.residual_weights()
        a, b = dr.gather(mi.Float64, ta, ridx), dr.gather(mi.Float64, tb, ridx)
        fa_, fb_ = dr.gather(mi.Float64, fa, ridx), dr.gather(mi.Float64, fb, ridx)
        side = dr.zeros(mi.Int32, dr.width(ridx))  # last endpoint replaced: -1 a, +1 b, 0 none

        def root(a, b, fa_, fb_):
            return dr.clip((a * fb_ - b * fa_) / (fb_ - fa_), a, b)

        for _ in range(cfg.refine_iterations):
            done = (b - a) <= cfg.depth_tolerance
            dr.scatter(t_out, root(a, b, fa_, fb_), ridx, done)
            keep = dr.compress(~done)
            if dr.width(keep) == 0:
                ridx = keep
                break
            ridx, a, b, fa_, fb_, side = (dr.gather(type(x), x, keep)
                                          for x in (ridx, a, b, fa_, fb_, side))
            tm = root(a, b, fa_, fb_)
            og, dg = dr.gather(mi.Point3d, o, ridx), dr.gather(mi.Vector3d, d, ridx)
            fm, _ = self._scene_sdf(dec, weights, mi.Point3d(og + tm * dg), dr.gather(mi.Float, time, ridx))
            exact = fm == 0
            left = fm > 0  # root lies in [tm, b]: replace a
            # Illinois: when the same endpoint is replaced twice in a row, halve the other's value
            fb_ = dr.select(left & (side == -1), 0.5 * fb_, fb_)
            fa_ = dr.select(~left & (side == 1), 0.5 * fa_, fa_)
            a, fa_ = dr.select(left | exact, tm, a), dr.select(left, fm, fa_)
            b, fb_ = dr.select(~left | exact, tm, b), dr.select(~left & ~exact, fm, fb_)
            side = dr.select(left, -1, 1)
        if dr.width(ridx) > 0:
            self.last_stats["refine_unconverged"] = dr.width(ridx)
            dr.scatter(t_out, root(a, b, fa_, fb_), ridx)
        return t_out

    def _shade(self, o, d, time, t: mi.Float64, hit: mi.Bool) -> tuple[mi.Int32, mi.Vector3f]:
        """Step 4: hit instance (``argmin_k F_k``) and unit normal, full width."""
        n = dr.width(o.x)
        instance = dr.full(mi.Int32, -1, n)
        normal = dr.zeros(mi.Vector3f, n)
        ridx = dr.compress(hit)
        m = dr.width(ridx)
        if m == 0:
            return instance, normal
        dec = self.field.decode()
        weights = self.field.residual_weights()
        tg = dr.gather(mi.Float, time, ridx)
        p = mi.Point3d(dr.gather(mi.Point3d, o, ridx)
                       + dr.gather(mi.Float64, t, ridx) * dr.gather(mi.Vector3d, d, ridx))
        _, arg = self._scene_sdf(dec, weights, p, tg)
        nrm = dr.zeros(mi.Vector3f, m)
        h = self.settings.normal_step
        for k in range(self.field.n):
            sel = dr.compress(arg == k)
            if dr.width(sel) == 0:
                continue
            pk, tk = dr.gather(mi.Point3d, p, sel), dr.gather(mi.Float, tg, sel)
            if weights is None:
                bv = self.field.view(dec, k, tk, dr.width(sel))
                nk = bv.dir_to_world(box_normal_local(mi.Vector3f(_to_local64(bv, pk)), bv.half))
            else:
                grad = []
                for axis in range(3):
                    e = mi.Vector3d(*[h if j == axis else 0.0 for j in range(3)])
                    grad.append(self._instance_sdf(dec, weights, k, mi.Point3d(pk + e), tk)
                                - self._instance_sdf(dec, weights, k, mi.Point3d(pk - e), tk))
                g = mi.Vector3d(*grad)
                nk = mi.Vector3f(g / dr.maximum(dr.norm(g), 1e-300))
            dr.scatter(nrm, nk, sel)
        dr.scatter(instance, arg, ridx)
        dr.scatter(normal, nrm, ridx)
        return instance, normal
