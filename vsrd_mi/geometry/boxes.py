"""3D boxes: the one implementation of box corners, yaw conventions and frame changes."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

#: KITTI-360 evaluation corner order: top face first (y = -1 in the y-down frame); signs of (x, y, z).
CORNER_SIGNS = np.array([
    [-1, -1, +1], [+1, -1, +1], [+1, -1, -1], [-1, -1, -1],
    [-1, +1, +1], [+1, +1, +1], [+1, +1, -1], [-1, +1, -1],
], dtype=np.float64)

#: The 12 edges of a box as index pairs into :data:`CORNER_SIGNS`.
BOX_EDGES = np.array([
    [0, 1], [1, 2], [2, 3], [3, 0],  # top face
    [4, 5], [5, 6], [6, 7], [7, 4],  # bottom face
    [0, 4], [1, 5], [2, 6], [3, 7],  # verticals
], dtype=np.int64)


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to ``[-pi, pi)``."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def axis_difference(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Angle (radians, in ``[0, pi/2]``) between the axes of yaws ``a`` and ``b``: their
    difference modulo pi (a box turned end for end has the same axis). Broadcasts."""
    d = np.abs(wrap_angle(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)))
    return np.minimum(d, np.pi - d)


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation ``R_y(yaw)`` about +y (y-down camera frame)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def kitti_ry_from_yaw(yaw: float) -> float:
    """KITTI ``rotation_y`` (heading along local +x) from our yaw (length along local +z)."""
    return float(wrap_angle(yaw - np.pi / 2.0))


def yaw_from_kitti_ry(ry: float) -> float:
    """Inverse of :func:`kitti_ry_from_yaw`."""
    return float(wrap_angle(ry + np.pi / 2.0))


def yaw_from_direction(direction: np.ndarray) -> float:
    """Yaw whose length axis points along the horizontal (x, z) part of ``direction``."""
    return float(np.arctan2(direction[0], direction[2]))


@dataclass(frozen=True)
class Box3D:
    """A gravity-aligned 3D box in some camera frame (see module conventions).

    ``size`` is the full extent ``(w, h, l)``; ``velocity`` is in metres per frame index and only
    used when ``dynamic`` is true.
    """

    centre: np.ndarray
    size: np.ndarray
    yaw: float
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dynamic: bool = False
    instance_id: int = -1

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", np.asarray(self.centre, dtype=np.float64).reshape(3))
        object.__setattr__(self, "size", np.asarray(self.size, dtype=np.float64).reshape(3))
        object.__setattr__(self, "velocity", np.asarray(self.velocity, dtype=np.float64).reshape(3))
        object.__setattr__(self, "yaw", float(self.yaw))
        if not (np.all(np.isfinite(self.centre)) and np.all(np.isfinite(self.size))
                and np.isfinite(self.yaw) and np.all(np.isfinite(self.velocity))):
            raise ValueError(f"non-finite box parameters: {self}")
        if np.any(self.size <= 0):
            raise ValueError(f"degenerate box size {self.size.tolist()} (all extents must be > 0)")

    @property
    def rotation(self) -> np.ndarray:
        return yaw_matrix(self.yaw)

    @property
    def heading(self) -> np.ndarray:
        """Unit vector of the length axis."""
        return self.rotation[:, 2].copy()

    def corners(self) -> np.ndarray:
        """The 8 corners, shape (8, 3), in :data:`CORNER_SIGNS` order."""
        return self.centre + (CORNER_SIGNS * (0.5 * self.size)) @ self.rotation.T

    def at_offset(self, dt: float) -> "Box3D":
        """The box ``dt`` frame indices later (moved by its velocity when dynamic)."""
        if not self.dynamic or dt == 0:
            return self
        return replace(self, centre=self.centre + self.velocity * dt)

    def transformed(self, T: np.ndarray) -> "Box3D":
        """The same box expressed in another frame; ``T`` (4x4) maps this frame to the new one.

        The new yaw is the heading of the transformed length axis projected to the new x-z plane
        (boxes stay gravity-aligned; a small camera pitch/roll between frames is ignored for the
        orientation but not for the centre).
        """
        T = np.asarray(T, dtype=np.float64)
        centre = T[:3, :3] @ self.centre + T[:3, 3]
        heading = T[:3, :3] @ self.heading
        velocity = T[:3, :3] @ self.velocity
        return replace(self, centre=centre, yaw=yaw_from_direction(heading), velocity=velocity)

    @property
    def bottom_centre(self) -> np.ndarray:
        """Centre of the bottom face (KITTI label location; y is down)."""
        return self.centre + np.array([0.0, 0.5 * self.size[1], 0.0])

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "size": self.size.tolist(), "yaw": self.yaw,
                "velocity": self.velocity.tolist(), "dynamic": bool(self.dynamic),
                "instance_id": int(self.instance_id)}

    @staticmethod
    def from_dict(d: dict) -> "Box3D":
        return Box3D(centre=d["centre"], size=d["size"], yaw=d["yaw"],
                     velocity=d.get("velocity", (0.0, 0.0, 0.0)), dynamic=d.get("dynamic", False),
                     instance_id=d.get("instance_id", -1))
