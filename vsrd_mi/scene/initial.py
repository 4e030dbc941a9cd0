"""Default initial boxes, used when no stereo initialisation (docs/method.md §6) is available.

Each target instance starts as a typical car standing where a car of typical height would appear
as tall as the instance's 2D box in the target image, facing along the road (the optimisation
frame's z axis, i.e. yaw 0), at rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.observations import Observations
from ..geometry.boxes import Box3D
from ..geometry.camera import transform_points


@dataclass(frozen=True)
class DefaultInitConfig:
    """The default initial box (values: a mid-size European hatchback/saloon)."""

    #: Full size ``(w, h, l)`` in metres.
    size: tuple[float, float, float] = (1.8, 1.5, 4.3)
    #: Car height (m) assumed to span the 2D box height; it sets the depth of the visible surface.
    height_for_depth: float = 1.5
    #: Added to that depth (m): the box centre lies behind the visible surface (about half a car width).
    centre_behind_surface: float = 0.9
    #: Depth range (m) the initial centre is clamped to (truncated or tiny 2D boxes give wild depths).
    min_depth: float = 3.0
    max_depth: float = 80.0
    #: Initial yaw (radians) in the optimisation frame: 0 = length axis along z, along the road.
    yaw: float = 0.0
    #: Initial velocity (m per frame index); instances start static.
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)


def default_initial_boxes(obs: Observations, cfg: DefaultInitConfig | None = None) -> list[Box3D]:
    """One box per target instance (in ``obs.instance_ids`` order) in the optimisation frame.

    The 2D box centre of the instance in the target frame (frame 0) is back-projected to depth
    ``fy * height_for_depth / box_height + centre_behind_surface`` (clamped), giving the centre.
    """
    cfg = cfg or DefaultInitConfig()
    K = obs.K[0]
    K_inv = np.linalg.inv(K)
    boxes = []
    for n, value in enumerate(obs.instance_ids):
        x1, y1, x2, y2 = obs.boxes2d[0, n]
        if not np.all(np.isfinite(obs.boxes2d[0, n])):
            raise ValueError(f"instance {value} has no mask in the target frame {obs.target}")
        depth = K[1, 1] * cfg.height_for_depth / (y2 - y1) + cfg.centre_behind_surface
        depth = float(np.clip(depth, cfg.min_depth, cfg.max_depth))
        centre_cam = depth * (K_inv @ np.array([0.5 * (x1 + x2), 0.5 * (y1 + y2), 1.0]))
        centre = transform_points(obs.cam_to_opt[0], centre_cam)
        boxes.append(Box3D(centre=centre, size=cfg.size, yaw=cfg.yaw, velocity=cfg.velocity,
                           dynamic=False, instance_id=int(value)))
    return boxes
