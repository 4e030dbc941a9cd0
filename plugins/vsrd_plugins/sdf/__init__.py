r"""Instance signed distance fields: boxes with velocity, plus an optional residual field.

The geometry behind ``vsrd_silhouette`` and ``sdf_tracer``. :class:`InstanceField` holds every
box of a scene as flat Dr.Jit parameters in physical units (the plugin properties of the same
names, listed by ``mi.traverse``):

============  =====  =========================================================================
name          size   meaning
============  =====  =========================================================================
``centre``    3N     box centre in the scene frame (scene units)
``size``      3N     full extents (width, height, length) along the box-local x, y, z axes
``yaw``       N      rotation about +y (radians); the length axis points along ``(sin, 0, cos)``
``velocity``  3N     scene units per unit of ray time
``dynamic``   N      1: the centre at ray time ``t`` is ``centre + velocity t``; 0: static
============  =====  =========================================================================

The scene frame is y-down (x right, y down, z forward; OpenCV-like). :mod:`.boxes` gives the
box SDF ``B`` and its exact behaviour along rays, :mod:`.residual` the residual field ``R``
(``F_n = B_n + R_n``, ``0 <= R_n <= r_max``), :mod:`.mlp` the residual MLP's layers and
hand-written derivatives. The scene SDF is ``F = min_n F_n``; the soft instance label at ``p``
is ``softmin_n(F_n(p) / tau)``, computed stably with the detached minimum subtracted.
"""

from __future__ import annotations

from ..common import concat, sigmoid, softplus
from .boxes import (BOX_RAY_KINKS, RIDGE_TOLERANCE, BoxView, DecodedBoxes, box_normal_local, box_ray_bends,
                    box_ray_kinks, box_sdf_local, box_sdf_local_grad, box_sdf_ray_local, envelope_blend, envelope_weight,
                    face_planes, ray_box_interval, ridge_faces, ridge_local_grad, scene_sdf, softmin_labels)
from .field import BOX_PARAMETERS, RESIDUAL_PREFIX, InstanceField
from .lane_gradient import lane_box_sdf
from .lattice import LATTICE_LOOKUP_COST, ResidualLattice, catmull_rom_weights
from .mlp import (FusedResidual, bucket_width, gelu, gelu_and_slope, layer_norm, layer_norm_and_scale,
                  layer_norm_derivative)
from .residual import ResidualConfig, ResidualField

__all__ = ["BOX_RAY_KINKS", "RIDGE_TOLERANCE", "BoxView", "DecodedBoxes", "box_normal_local", "box_ray_bends",
           "box_ray_kinks", "box_sdf_local", "box_sdf_local_grad", "box_sdf_ray_local", "envelope_blend", "envelope_weight",
           "face_planes", "ray_box_interval", "ridge_faces", "ridge_local_grad", "scene_sdf", "softmin_labels",
           "BOX_PARAMETERS", "RESIDUAL_PREFIX", "InstanceField", "lane_box_sdf", "LATTICE_LOOKUP_COST", "ResidualLattice", "catmull_rom_weights", "FusedResidual",
           "bucket_width", "gelu", "gelu_and_slope", "layer_norm", "layer_norm_and_scale", "layer_norm_derivative",
           "ResidualConfig", "ResidualField", "concat", "sigmoid", "softplus"]
