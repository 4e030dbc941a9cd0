"""vsrd_plugins: Mitsuba 3 integrators for instance-aware SDF silhouette rendering.

Self-contained: depends only on Mitsuba 3 and Dr.Jit (no vsrd-mi pipeline code), so this folder
can be copied into another project. Modules:

* :mod:`vsrd_plugins.sdf` -- instance SDF model (boxes with velocity + hypernetwork residual field).
* :mod:`vsrd_plugins.silhouette` -- ``vsrd_silhouette``: NeuS instance-aware silhouette integral.
* :mod:`vsrd_plugins.tracer` -- ``sdf_tracer``: sphere-traced instance id / depth / normal.

Call :func:`register` after ``mi.set_variant(...)`` (an ``*_ad_rgb`` variant) to make the
integrators available to ``mi.load_dict`` / ``mi.load_file``.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def register(disable_packet_ops: bool = True) -> None:
    """Register ``vsrd_silhouette`` and ``sdf_tracer`` for the current Mitsuba variant.

    ``disable_packet_ops`` turns off Dr.Jit's ``JitFlag.PacketOps``: with it on, the LLVM backend
    specialises kernel loads on the run-time alignment of every input buffer, and the many
    differently sized arrays these integrators create per call (compacted rays, per-band groups)
    made 10-20 kernels recompile on *every* optimisation step (~4 s of LLVM time per step,
    measured with ``dr.kernel_history()``); with it off, 0 recompilations after warm-up.
    """
    if disable_packet_ops:
        dr.set_flag(dr.JitFlag.PacketOps, False)
    from .silhouette import VSRDSilhouetteIntegrator
    from .tracer import SDFTracerIntegrator

    mi.register_integrator("vsrd_silhouette", lambda props: VSRDSilhouetteIntegrator(props))
    mi.register_integrator("sdf_tracer", lambda props: SDFTracerIntegrator(props))
