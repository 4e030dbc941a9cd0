"""The instance field: every box of a scene (with velocity) and the optional residual field."""

from __future__ import annotations

from typing import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from ..properties import PropertyError, read_bool, read_floats, read_int
from .boxes import (BoxView, DecodedBoxes, box_sdf_local, box_sdf_ray_local, ridge_faces)
from .lane_gradient import lane_box_sdf
from .residual import ResidualConfig, ResidualField


#: The box parameters: name, values per box, whether differentiable. The names are the plugin
#: properties and the keys under which ``mi.traverse`` lists them.
BOX_PARAMETERS = (("centre", 3, True), ("size", 3, True), ("yaw", 1, True), ("velocity", 3, True),
                  ("dynamic", 1, False))
#: Prefix of the residual field's parameters in ``mi.traverse``.
RESIDUAL_PREFIX = "rdf_"


class InstanceField:
    """Every box of a scene in physical units, and the optional residual field.

    Box parameters (flat Dr.Jit Floats, box-major; :data:`BOX_PARAMETERS`): ``centre`` (3N, scene
    units), ``size`` (3N, full extents along the box-local x, y, z: width, height, length),
    ``yaw`` (N, radians about +y), ``velocity`` (3N, scene units per unit of ray time) and
    ``dynamic`` (N, 0 or 1): a box's centre at ray time ``t`` is ``centre + dynamic * velocity *
    t``. A box is what these say: nothing clamps or reparameterises them. With the residual
    field (``residual``) its embedding and hypernetwork weights are parameters too
    (``rdf_embedding``, ``rdf_hyper_w{i}``, ``rdf_hyper_b{i}``); :attr:`use_residual` pauses
    the field without removing them.
    """

    def __init__(self, props, plugin: str):
        self.plugin = plugin
        present = "centre" in props or "size" in props
        centre = read_floats(props, plugin, "centre") if present else np.zeros(0)
        if centre.size % 3:
            raise PropertyError(f"{plugin}: property 'centre' has {centre.size} values, expected 3 per box")
        n = self.n = centre.size // 3
        size = read_floats(props, plugin, "size", 3 * n, positive=True) if present else np.zeros(0)
        values = {"centre": centre, "size": size, "yaw": read_floats(props, plugin, "yaw", n, 0.0),
                  "velocity": read_floats(props, plugin, "velocity", 3 * n, 0.0),
                  "dynamic": read_floats(props, plugin, "dynamic", n, 0.0)}
        if not np.all(np.isin(values["dynamic"], (0.0, 1.0))):
            raise PropertyError(f"{plugin}: property 'dynamic' must hold 0 or 1 per box")
        # from Python lists: Dr.Jit-owned memory (a NumPy buffer's alignment can enter kernel hashes)
        self.params: dict[str, mi.Float] = {k: mi.Float(v.astype(np.float32).tolist()) for k, v in values.items()}
        self.residual = None
        seed = read_int(props, plugin, "residual_seed", 0, 0)
        if read_bool(props, plugin, "residual", False) and n:
            self.residual = ResidualField(n, ResidualConfig(seed=seed))
        #: Whether the residual field is evaluated (it exists only with the ``residual`` property).
        self.use_residual = self.residual is not None

    # -- parameters ------------------------------------------------------------------------
    def traverse(self, cb: mi.TraversalCallback) -> None:
        """Put every box parameter and, with the residual field, its parameters."""
        for name, _, differentiable in BOX_PARAMETERS:
            cb.put(name, self.params[name],
                   mi.ParamFlags.Differentiable if differentiable else mi.ParamFlags.NonDifferentiable)
        if self.residual is not None:
            for k, v in self.residual.params.items():
                cb.put(RESIDUAL_PREFIX + k, v, mi.ParamFlags.Differentiable)

    def check_parameters(self) -> None:
        """Raise a :class:`~vsrd_plugins.properties.PropertyError` naming a box parameter whose
        width no longer fits the box count (after an assignment through ``mi.traverse``)."""
        for name, per_box, _ in BOX_PARAMETERS:
            width = dr.width(self.params[name])
            if width != per_box * self.n:
                raise PropertyError(f"{self.plugin}: parameter '{name}' has {width} values, expected "
                                    f"{per_box * self.n} ({per_box} per box, {self.n} boxes)")

    @property
    def residual_reach(self) -> float:
        """Largest amount by which the residual can raise an instance SDF (0 when off)."""
        return self.residual.cfg.max_residual if (self.use_residual and self.residual) else 0.0

    # -- boxes -------------------------------------------------------------------------------
    def decode(self) -> DecodedBoxes:
        """The boxes as per-axis width-N arrays (half extents, ``cos`` / ``sin`` of the yaw),
        differentiable w.r.t. the parameters."""
        # opaque: with one box, ``yaw`` and ``dynamic`` hold one value each, and Dr.Jit bakes the
        # value of a width-1 array into the kernels that read it (new kernels for every new yaw)
        dr.make_opaque(*self.params.values())
        return self.decode_parameters(self.params, self.n)

    @staticmethod
    def decode_parameters(params, n: int) -> DecodedBoxes:
        """:meth:`decode` of box parameters given as a mapping with the keys of
        :data:`BOX_PARAMETERS` (flat, box-major) for ``n`` boxes: what a caller that holds the
        parameters itself (e.g. inside a ``dr.freeze`` function) decodes them with."""
        idx = [dr.arange(mi.UInt32, n) * 3 + j for j in range(3)]
        half = [0.5 * dr.gather(mi.Float, params["size"], i) for i in idx]
        centre = [dr.gather(mi.Float, params["centre"], i) for i in idx]
        vel = [dr.gather(mi.Float, params["velocity"], i) for i in idx]
        sin, cos = dr.sincos(params["yaw"])
        return DecodedBoxes(half, centre, cos, sin, vel, mi.Float(params["dynamic"]))

    def boxes(self) -> dict[str, np.ndarray]:
        """The box parameters as NumPy arrays: ``centre`` (N, 3), ``size`` (N, 3), ``yaw`` (N,),
        ``velocity`` (N, 3), ``dynamic`` (N,)."""
        return {name: np.array(dr.detach(self.params[name]), dtype=np.float64).reshape((self.n, 3) if per_box == 3
                                                                                          else (self.n,))
                for name, per_box, _ in BOX_PARAMETERS}

    def view(self, dec: DecodedBoxes, k: int, time: mi.Float, width: int) -> BoxView:
        """Instance ``k`` broadcast to ``width`` lanes at per-lane ray time ``time``."""
        return self.view_lanes(dec, dr.full(mi.UInt32, k, width), time)

    @staticmethod
    def view_lanes(dec: DecodedBoxes, inst: mi.UInt32, time: mi.Float) -> BoxView:
        """Instance ``inst[i]`` at lane ``i`` (per-lane gathers) at per-lane ray time ``time``."""

        def g(a):
            # the reverse of this gather is a scatter-add of every lane into an array of
            # num_instances entries: Expand (per-thread copies, no atomics) instead of atomics
            # contended by every lane; the target size is fixed per scene, so nothing recompiles
            return dr.gather(mi.Float, a, inst, mode=dr.ReduceMode.Expand)

        m = g(dec.dynamic) * time
        centre = mi.Point3f(*[g(dec.centre[j]) + m * g(dec.velocity[j]) for j in range(3)])
        return BoxView(mi.Vector3f(*[g(h) for h in dec.half]), centre, g(dec.cos), g(dec.sin))

    # -- evaluation --------------------------------------------------------------------------
    def residual_weights(self) -> mi.TensorXf | None:
        if not (self.use_residual and self.residual is not None):
            return None
        return self.residual.generate_weights()

    def instance_sdfs(self, dec: DecodedBoxes, p: mi.Point3f, time: mi.Float,
                      weights: mi.TensorXf | None = None, reach: float | mi.Float = 0.0,
                      instances: Sequence[int] | None = None) -> list[mi.Float]:
        """SDF of every instance at points ``p`` (scene frame) at ray times ``time``.

        With ``weights`` (from :meth:`residual_weights`) the residual is added wherever the point
        lies inside the instance's box enlarged by ``reach`` in every local axis; elsewhere the
        residual can only raise an SDF that is already ``>= reach`` and is skipped.
        """
        width = dr.width(p.x)
        ks = list(range(self.n) if instances is None else instances)
        out, parts = [], []
        for k in ks:
            bv = self.view(dec, k, time, width)
            pl = bv.to_local(p)
            out.append(box_sdf_local(pl, bv.half))
            if weights is not None:
                parts.append((k, pl, _near_box(pl, bv.half, reach)))
        if weights is None:
            return out
        for i, lanes, r in self._residuals(weights, parts):
            extra = dr.zeros(mi.Float, width)
            dr.scatter_add(extra, r, lanes)
            out[i] = out[i] + extra
        return out

    def lane_sdfs(self, dec: DecodedBoxes, p: mi.Point3f, time: mi.Float, inst: mi.UInt32,
                  weights: mi.TensorXf | None = None, reach: float | mi.Float = 0.0,
                  ridge: tuple[mi.UInt32, mi.Vector3f, float | mi.Float] | None = None,
                  grad_reach: float | mi.Float | None = None) -> mi.Float:
        """SDF of instance ``inst[i]`` at point ``p[i]`` (one instance per lane).

        The per-lane counterpart of :meth:`instance_sdfs` for samplers that evaluate only the
        instances a ray can meet; the residual is added under the same ``reach`` rule. With
        ``ridge = (lanes, ray directions, tolerance)`` the box part at those lanes, each the
        deepest point of its ray in its lane's box, carries the envelope gradient
        (:func:`box_sdf_ray_local`; same values). With ``grad_reach``, lanes outside the box
        enlarged by ``grad_reach`` (and by ``reach`` with a residual) get the detached box SDF:
        the same values, but only the lanes near their box enter the AD graph (the backward pass
        runs over those alone; the box part's gradient is computed in closed form,
        :func:`~.lane_gradient.lane_box_sdf`, ridge lanes included, which then must lie within
        ``grad_reach`` of their box: a deepest point inside it does). A sampler may pass the
        distance beyond which an SDF value can no longer move its integral.
        """
        if grad_reach is None:
            f = self.lane_sdfs_ad(dec, p, time, inst, weights, reach)
        else:
            with dr.suspend_grad():
                bv = self.view_lanes(dec, inst, time)
                f = box_sdf_local(bv.to_local(p), bv.half)
                # the residual only raises the box SDF: lanes whose box SDF exceeds the reach
                # stay beyond it
                live_reach = grad_reach if weights is None else dr.maximum(grad_reach, reach)
                near = f <= live_reach
                dr.eval(f, near)  # one kernel for both (compress would evaluate the mask alone)
                live = dr.compress(near)
            if dr.width(live):
                f = lane_box_sdf(dec, f, p, time, inst, live, None if ridge is None else
                                 self._ridge_lanes(dec, p, time, inst, ridge))
                if weights is not None:
                    f = f + self._lane_residuals(dec, p, time, inst, weights, reach, live)
            return f
        if ridge is not None:
            f = f + self.ridge_correction(dec, p, time, inst, ridge)
        return f

    def _ridge_lanes(self, dec: DecodedBoxes, p: mi.Point3f, time: mi.Float, inst: mi.UInt32,
                     ridge: tuple[mi.UInt32, mi.Vector3f, float | mi.Float]) -> tuple[mi.UInt32, mi.Float]:
        """Per lane the ridge faces ``8 a + b`` and ``lambda_a`` (:func:`ridge_faces`) at the
        lanes ``ridge[0]`` (ray directions ``ridge[1]``, face tolerance ``ridge[2]``, and
        optionally per lane a kink's weight ``ridge[3]``, ``-1`` for none) that lie on a ridge;
        ``lambda = -1`` elsewhere (detached)."""
        lanes, dirs, tol, kink_lam = _ridge_parts(ridge)
        width = dr.width(p.x)
        with dr.suspend_grad():
            pr, tr, ir = (dr.gather(type(p), p, lanes), dr.gather(mi.Float, time, lanes),
                          dr.gather(mi.UInt32, inst, lanes))
            bv = self.view_lanes(dec, ir, tr)
            on, ia, ib, lam = ridge_faces(bv.to_local(pr), bv.dir_to_local(dirs), bv.half, tol, kink_lam)
            faces, lams = dr.zeros(mi.UInt32, width), dr.full(mi.Float, -1.0, width)
            dr.scatter(faces, ia * 8 + ib, lanes)
            dr.scatter(lams, dr.select(on, lam, -1.0), lanes)
        return faces, lams

    def _lane_residuals(self, dec: DecodedBoxes, p: mi.Point3f, time: mi.Float, inst: mi.UInt32,
                        weights: mi.TensorXf, reach: float | mi.Float, live: mi.UInt32) -> mi.Float:
        """Residual of instance ``inst[i]`` at ``p[i]`` on the lanes ``live`` (0 elsewhere),
        differentiable w.r.t. the boxes (its input is the box-local point) and the field."""
        with dr.suspend_grad():
            p_s, t_s, i_s = (dr.gather(type(p), p, live), dr.gather(mi.Float, time, live),
                             dr.gather(mi.UInt32, inst, live))
        bv = self.view_lanes(dec, i_s, t_s)
        extra = dr.zeros(mi.Float, dr.width(p.x))
        dr.scatter_add(extra, self._residual_at(weights, bv.to_local(p_s), bv.half, i_s, reach), live)
        return extra

    def _residual_at(self, weights: mi.TensorXf, pl: mi.Vector3f, half: mi.Vector3f, inst: mi.UInt32,
                     reach: float | mi.Float) -> mi.Float:
        """Residual of instance ``inst[i]`` at box-local ``pl[i]`` where it lies inside the box
        enlarged by ``reach`` (0 elsewhere)."""
        near = _near_box(pl, half, reach)
        # the instances' lane sets are disjoint: one array takes every residual
        extra = dr.zeros(mi.Float, dr.width(pl.x))
        for _, lanes, r in self._residuals(weights, [(k, pl, near & (inst == k)) for k in range(self.n)]):
            dr.scatter_add(extra, r, lanes)
            dr.eval(extra)  # one kernel per instance: pending scatters of equal width share one
        return extra

    def lane_sdfs_ad(self, dec: DecodedBoxes, p: mi.Point3f, time: mi.Float, inst: mi.UInt32,
                      weights: mi.TensorXf | None, reach: float | mi.Float) -> mi.Float:
        """Differentiable box SDF (+ residual under the ``reach`` rule) of one instance per lane."""
        bv = self.view_lanes(dec, inst, time)
        pl = bv.to_local(p)
        f = box_sdf_local(pl, bv.half)
        return f if weights is None else f + self._residual_at(weights, pl, bv.half, inst, reach)

    def ridge_correction(self, dec: DecodedBoxes, p: mi.Point3f, time: mi.Float, inst: mi.UInt32,
                         ridge: tuple[mi.UInt32, mi.Vector3f, float | mi.Float]) -> mi.Float:
        """Zero-valued term that turns the box gradient at lanes ``ridge[0]`` (each the deepest
        point of its ray in its lane's box; ray directions ``ridge[1]``, face tolerance
        ``ridge[2]``) into the envelope gradient of :func:`box_sdf_ray_local`; only those lanes
        pay for it. ``inst`` holds each lane's instance (one value: every lane); an optional
        ``ridge[3]`` gives kinks their own weights (:func:`ridge_faces`)."""
        lanes, dirs, tol, kink_lam = _ridge_parts(ridge)
        with dr.suspend_grad():
            pr = dr.gather(type(p), p, lanes)
            tr = dr.gather(mi.Float, time, lanes)
            ir = inst if dr.width(inst) == 1 else dr.gather(mi.UInt32, inst, lanes)
        bv = self.view_lanes(dec, ir, tr)
        pl = bv.to_local(pr)
        delta = (box_sdf_ray_local(pl, dr.detach(bv.dir_to_local(dirs)), bv.half, tol, kink_lam)
                 - box_sdf_local(pl, bv.half))
        out = dr.zeros(mi.Float, dr.width(p.x))
        dr.scatter_add(out, delta, lanes)
        return out

    def _residuals(self, weights: mi.TensorXf, parts: list) -> list[tuple[int, mi.UInt32, mi.Float]]:
        """Residuals of ``parts = [(instance, box-local points, mask)]`` where the masks hold, all
        instances in one batched MLP evaluation: ``(part index, lanes, values)`` per non-empty part."""
        # masks and points in one kernel: a compress (or gather) of an unevaluated array
        # evaluates it alone, and the per-instance masks of the lane path share their points, so
        # each instance's compress recomputed every lane's box-local point (6 boxes / 16k rays:
        # 6 kernels of 0.96M lanes, 68 ms of a 0.19 s pass)
        dr.eval([mask for _, _, mask in parts], [p for _, p, _ in parts])
        idxs = [dr.compress(mask) for _, _, mask in parts]
        live = [i for i, idx in enumerate(idxs) if dr.width(idx) > 0]
        if not live:
            return []
        pts = [mi.Vector3f(*[dr.gather(mi.Float, c, idxs[i]) for c in parts[i][1]]) for i in live]
        res = self.residual.evaluate_grouped(weights, [parts[i][0] for i in live], pts)
        return [(i, idxs[i], r) for i, r in zip(live, res)]


def _ridge_parts(ridge: tuple) -> tuple:
    """``(lanes, directions, tolerance, kink weights or None)`` of a ``ridge`` argument of
    :meth:`InstanceField.lane_sdfs` (the kink weights ``ridge[3]`` are optional)."""
    return (*ridge[:3], ridge[3] if len(ridge) > 3 else None)


def _near_box(p_local: mi.Vector3f, half: mi.Vector3f, reach) -> mi.Bool:
    """Points inside the box enlarged by ``reach`` in every local axis (detached mask)."""
    with dr.suspend_grad():
        return dr.all(dr.abs(p_local) <= half + reach)

