r"""Instance signed distance fields: boxes with velocity plus a hypernetwork residual field.

This module is the geometry behind the ``vsrd_silhouette`` and ``sdf_tracer`` integrators. It
depends only on Mitsuba 3 and Dr.Jit.

Box parameters (instance-major flat Dr.Jit arrays, all differentiable except ``dynamic``)
-----------------------------------------------------------------------------------------

=================  =====  =====================================================================
name               size   decoding
=================  =====  =====================================================================
``box_dims``       3N     half-extents ``d = lo + (hi - lo) * sigmoid(raw)`` (:class:`BoxRanges`)
``box_centre``     3N     centre ``l = lo + (hi - lo) * sigmoid(raw)`` in the scene frame
``box_yaw``        2N     unnormalised ``(cos, sin)`` of the yaw about +y, normalised at use
``box_velocity``   3N     velocity ``v`` in scene units per unit of ray time (frame index)
``box_dynamic``    N      ``m`` in {0, 1}; the centre at ray time ``t`` is ``l + m v t``
=================  =====  =====================================================================

The scene frame is y-down (OpenCV-like: x right, y down, z forward); the yaw rotation is
``R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]]`` so the box length axis (local +z) points along
``(s, 0, c)``.

Box SDF (REFERENCE §2), in box-local coordinates ``q = |p_local| - d``:

.. math::

    B(p) = \sqrt{\lVert \max(q, 0) \rVert^2} + \min(\max(q_x, q_y, q_z), 0)

with a safe square root whose derivative at 0 is 0, so points inside the box, on faces and on
edges have finite gradients.

Residual distance field (RDF)
-----------------------------

``F_n(p) = B_n(p) + R_n(p)`` with ``R_n(p) = r_max * sigmoid(G(x; phi_n) - shift) >= 0`` so the
surface stays inside its box. ``G`` is a small per-instance MLP (48 -> 16 -> 16 -> 16 -> 16 -> 1,
GELU, parameter-free layer norm before each hidden activation) whose 1617 weights
``phi_n = H(z_n; psi)`` come from a shared hypernetwork ``H`` (256 -> 4 x (256, LayerNorm, GELU)
-> 1617) applied to a learnable embedding ``z_n``. The input ``x`` is the box-local point
mirrored in x (left/right symmetry), scaled by ``1/100`` and encoded with 8 sinusoidal
frequencies ``2^k pi`` (48 features). We use the shifted sigmoid of the authors' code rather than
the paper's softplus: it bounds the residual's reach by ``r_max``, which is what lets the
integrators cull instances with a box enlarged by a known margin. ``shift`` (default 3) starts
the residual near ``0.05 r_max`` so switching the field on does not shrink every silhouette.

On the LLVM backend each instance's MLP runs as one fused kernel of cooperative-vector matvecs;
where a gradient is needed its derivatives are written out (:class:`_FusedResidual`: one kernel
for the adjoints, a GEMM per layer for the weight gradient), because a coop matvec uses one
weight matrix per kernel and Dr.Jit's own coop backward accumulates weight gradients with atomics
(DRJIT.md: 2-3x slower than tensor mode on x86). Dr.Jit AD through *tensor-mode* batched GEMMs is
the reference and the path on other backends (``ResidualConfig.gradients``). Points are grouped
per instance and the residual is only evaluated where it can change the result (inside the
instance's box enlarged by the caller's reach), see :meth:`InstanceField.instance_sdfs`.

Scene SDF and labels
--------------------

``F(p) = min_n F_n(p)``; the soft instance label at ``p`` is
``softmin_n(F_n(p) / tau)``, computed stably as ``exp((m - F_n)/tau) / sum_k exp((m - F_k)/tau)``
with ``m = min_k F_k`` detached.
"""


from ..common import concat, sigmoid, softplus
from ..properties import instance_properties
from .boxes import (BOX_RAY_KINKS, RIDGE_TOLERANCE, BoxRanges, BoxView, DecodedBoxes, box_normal_local, box_ray_bends,
                    box_ray_kinks, box_sdf_local, box_sdf_local_grad, box_sdf_ray_local, envelope_blend, envelope_weight,
                    face_planes, logit_np, ray_box_interval, ridge_faces, ridge_local_grad, scene_sdf, softmin_labels)
from .field import InstanceField
from .lane_gradient import lane_box_sdf
from .lattice import LATTICE_LOOKUP_COST, ResidualLattice, catmull_rom_weights
from .mlp import (FusedResidual, bucket_width, gelu, gelu_and_slope, layer_norm, layer_norm_and_scale,
                  layer_norm_derivative)
from .residual import ResidualConfig, ResidualField

__all__ = ["BOX_RAY_KINKS", "RIDGE_TOLERANCE", "BoxRanges", "BoxView", "DecodedBoxes", "box_normal_local", "box_ray_bends",
           "box_ray_kinks", "box_sdf_local", "box_sdf_local_grad", "box_sdf_ray_local", "envelope_blend", "envelope_weight",
           "face_planes", "logit_np", "ray_box_interval", "ridge_faces", "ridge_local_grad", "scene_sdf", "softmin_labels",
           "InstanceField", "lane_box_sdf", "LATTICE_LOOKUP_COST", "ResidualLattice", "catmull_rom_weights", "FusedResidual",
           "bucket_width", "gelu", "gelu_and_slope", "layer_norm", "layer_norm_and_scale", "layer_norm_derivative",
           "ResidualConfig", "ResidualField", "concat", "sigmoid", "softplus", "instance_properties"]
