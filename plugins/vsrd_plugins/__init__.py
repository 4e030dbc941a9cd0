"""vsrd_plugins: Mitsuba 3 integrators for instance-aware box silhouettes, differentiable w.r.t.
the boxes.

Needs only Mitsuba 3, Dr.Jit and NumPy: copy this folder into another project and
``import vsrd_plugins``. After ``mi.set_variant(...)`` (an ``*_ad_rgb`` variant) call
:func:`register`; then ``mi.load_dict`` / ``mi.load_file`` know the integrators

* ``vsrd_silhouette`` (:mod:`vsrd_plugins.silhouette`): soft instance labels (one AOV per box)
  from a NeuS integral over the boxes' signed distance, for fitting boxes to instance masks
  with ``mi.traverse`` and an optimiser;
* ``sdf_tracer`` (:mod:`vsrd_plugins.tracer`): sphere-traced instance id, depth and normal of
  the same boxes, for inspection.

Both read the boxes from the same properties (``centre``, ``size``, ``yaw``, ``velocity``,
``dynamic``; :func:`box_properties` builds them from lists or NumPy arrays) and list them in
``mi.traverse`` in physical units. :mod:`vsrd_plugins.sdf` holds the geometry (box SDF, the
residual field), :mod:`vsrd_plugins.common` the shared numerics and searches.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .properties import PropertyError, box_properties

__all__ = ["register", "restore_jit_settings", "box_properties", "PropertyError"]


def register(jit_settings: bool = True) -> dict[str, object]:
    """Register ``vsrd_silhouette`` and ``sdf_tracer`` for the current Mitsuba variant.

    With ``jit_settings`` (the default) this also changes two **process-wide** Dr.Jit settings,
    for every kernel of the process from then on, and returns their previous values
    (:func:`restore_jit_settings` puts them back):

    * ``dr.JitFlag.PacketOps`` off. With it on, the LLVM backend specialises kernel loads on
      the run-time alignment of every input buffer, and the many differently sized arrays these
      integrators create per call (compacted rays, per-band sample groups) made 10-20 kernels
      compile anew on every optimisation step (about 4 s of LLVM time per step, seen in
      ``dr.kernel_history()``); with it off, none after the first steps.
    * ``dr.set_expand_threshold(0)``. The LLVM backend otherwise compiles scatter-additions into
      targets of up to 2^20 entries in ``ReduceMode.Expand``, which bakes the target's size into
      the kernel. The backward pass of every gather from a per-call sized array is such a
      scatter-addition, so with fresh rays every step 3-10 kernels compiled anew per step (a
      box-only optimisation step of the bundled scene took 3.7 s instead of 0.35 s).

    The backward pass runs where the caller calls ``dr.backward``, outside any call of the
    integrators, so the settings cannot be scoped to their calls. Pass ``jit_settings=False``
    to keep the process's settings (expect the recompilations above).
    """
    previous = {"PacketOps": dr.flag(dr.JitFlag.PacketOps), "expand_threshold": dr.expand_threshold()}
    if jit_settings:
        dr.set_flag(dr.JitFlag.PacketOps, False)
        dr.set_expand_threshold(0)
        mi.Log(mi.LogLevel.Info, "vsrd_plugins.register(): Dr.Jit PacketOps off and expand threshold 0 for this "
                                 "process (see its docstring)")
    # imported here, not at the top: the integrator classes derive from ``mi.ad`` classes,
    # which exist only once a variant is set (importing vsrd_plugins itself needs none)
    from .silhouette import VSRDSilhouetteIntegrator
    from .tracer import SDFTracerIntegrator

    mi.register_integrator("vsrd_silhouette", lambda props: VSRDSilhouetteIntegrator(props))
    mi.register_integrator("sdf_tracer", lambda props: SDFTracerIntegrator(props))
    return previous


def restore_jit_settings(previous: dict[str, object]) -> None:
    """Put back the Dr.Jit settings :func:`register` returned."""
    dr.set_flag(dr.JitFlag.PacketOps, bool(previous["PacketOps"]))
    dr.set_expand_threshold(int(previous["expand_threshold"]))
