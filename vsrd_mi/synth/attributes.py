"""Per-car attributes of a synthetic sequence: class, parking, occlusion and truncation.

Written next to the 3D-box XML as ``data_3d_bboxes/train/<seq>.attributes.json``::

    {"format": "vsrd-mi attributes 1",
     "instances": {"26001": {"vehicle_class": "sedan", "dynamic": false,
                             "parking": "parallel", "angle_to_road_deg": 0.0}},
     "frames": {"12": {"26001": {"occlusion": 0.42, "truncation": 0.0}}}}

Keys are instance-map values as strings (26000 + instanceId) and frame numbers as strings. For
every frame, every car whose silhouette reaches into the left image gets an entry:

- occlusion = 1 - visible / amodal pixels, where amodal pixels are those of the car rendered
  alone inside the image and visible ones those the instance map gives the car;
- truncation = share of the car's amodal silhouette that lies outside the image, rendered
  alone on a margin around the image (:class:`~vsrd_mi.synth.config.VisibilityConfig`: one image
  size beyond each border by default, every ``margin_stride``-th pixel of each direction). Where
  the silhouette reaches past the margin (a car right beside the camera, or partly behind it)
  the share is taken within the margin, a lower bound.

Cheap by construction: the cars stand apart in one "showroom" scene, each in its own frame, and
each car's rays are cast only through the pixels of its projected mesh's bounding rectangle (of
its 3D box when part of it is behind the camera), all cars of a frame in one launch. A car whose
rectangle covers more than ``max_rays_per_car`` pixels is sampled on a sparser pixel grid, the
same grid for its visible and its amodal count.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry.camera import NEAR_PLANE, box_to_2d, project
from .render import RayCaster
from .world import WORLD_TO_G, SynthCar, SynthWorld

#: The ``format`` string of the attributes file.
ATTRIBUTES_FORMAT = "vsrd-mi attributes 1"
#: Distance added to a car's reach (metres) and between two showroom slots beyond their reach.
SHOWROOM_MARGIN = 10.0


def attributes_path(root: str | Path, sequence: str) -> Path:
    """``<root>/data_3d_bboxes/train/<sequence>.attributes.json``."""
    return Path(root) / "data_3d_bboxes" / "train" / f"{sequence}.attributes.json"


@dataclass(frozen=True)
class CarVisibility:
    """How much of a car one frame shows (left camera)."""

    instance_value: int  # pixel value in the instance map
    visible_px: int  # pixels labelled with this car in the instance map
    inside_px: int  # pixels of the car rendered alone that fall inside the image
    outside_px: float  # estimated pixels of the car alone beyond the borders, within the margin
    #: part of the car's box lies behind the camera's near plane, or its projection reaches past
    #: the rendered margin (the truncation is then a lower bound)
    beyond_margin: bool

    @property
    def occluded_fraction(self) -> float:
        """Share of the car's in-image silhouette hidden by other geometry (1 if none inside)."""
        return 1.0 - self.visible_px / self.inside_px if self.inside_px else 1.0

    @property
    def truncated_fraction(self) -> float:
        """Share of the car's silhouette (within the margin) outside the image."""
        total = self.inside_px + self.outside_px
        return float(self.outside_px / total) if total > 0 else 0.0

    @property
    def truncated(self) -> bool:
        return self.outside_px > 0 or self.beyond_margin


class AmodalCaster:
    """Renders every car of a world alone: one scene with each car at its own far-apart slot.

    A car's rays are moved into its model frame plus its slot; the slots lie further apart than
    any ray can travel before it meets its own car, and a hit counts only within that reach.
    """

    def __init__(self, world: SynthWorld):
        self.world = world
        cars = world.cars
        centres = np.array([T[:3, 3] for T in world.cam0_to_world])
        dist = max((float(np.linalg.norm(centres - car.centre0 - np.outer(
            np.arange(len(centres)), car.velocity), axis=1).max()) for car in cars), default=0.0)
        diag = max((float(np.linalg.norm(car.size_lwh)) for car in cars), default=0.0)
        self.reach = dist + diag + SHOWROOM_MARGIN
        spacing = 2.0 * self.reach + 2.0 * diag + SHOWROOM_MARGIN
        cols = max(int(np.ceil(np.sqrt(len(cars)))), 1)
        self.slots = np.array([[spacing * (k % cols), spacing * (k // cols), 0.0]
                               for k in range(len(cars))]).reshape(-1, 3)
        verts, faces, offset = [], [], 0
        for car, slot in zip(cars, self.slots):
            verts.append(car.model.vertices + slot)
            faces.append(car.model.faces + offset)
            offset += len(car.model.vertices)
        self.caster = RayCaster(np.concatenate(verts), np.concatenate(faces)) if cars else None

    def frame(self, i: int, instance_map: np.ndarray) -> list[CarVisibility]:
        """Visibility of every car at frame index ``i`` given the left view's instance map."""
        world, vis = self.world, self.world.config.visibility
        (w, h), K = world.rig.image_size, world.rig.K
        T = world.cam_to_world(i, 0)
        world_to_cam = np.linalg.inv(T)
        k_inv = np.linalg.inv(K)
        lo_lim = -np.floor(vis.margin * np.array([w, h]))
        hi_lim = np.array([w, h]) - 1 - lo_lim
        out = [CarVisibility(car.global_id, 0, 0, 0.0, False) for car in world.cars]
        origins, dirs, rays = [], [], []
        for ci, car in enumerate(world.cars):
            rect, behind = _projected_rect(world, car, i, world_to_cam)
            if rect is None:
                out[ci] = CarVisibility(car.global_id, 0, 0, 0.0, behind)
                continue
            lo, hi = np.ceil(rect[:2]), np.floor(rect[2:])
            clipped = bool(np.any(lo < lo_lim) or np.any(hi > hi_lim))
            out[ci] = CarVisibility(car.global_id, 0, 0, 0.0, behind or clipped)
            lo, hi = np.maximum(lo, lo_lim), np.minimum(hi, hi_lim)
            span = np.minimum(hi, [w - 1, h - 1]) - np.maximum(lo, 0) + 1
            if np.any(span <= 0):
                continue
            step = max(1, int(np.ceil(np.sqrt(span[0] * span[1] / vis.max_rays_per_car))))
            uv_in, uv_out = _box_pixels(lo, hi, (w, h), step, max(step, vis.margin_stride))
            uv = np.concatenate([uv_in, uv_out])
            d_local = np.column_stack([uv, np.ones(len(uv))]) @ k_inv.T @ T[:3, :3].T \
                @ car.rotation()
            d_local /= np.linalg.norm(d_local, axis=1, keepdims=True)
            origins.append(np.broadcast_to(car.to_local(T[:3, 3][None, :], i)[0] + self.slots[ci],
                                           d_local.shape))
            dirs.append(d_local)
            rays.append((ci, uv.astype(np.int64), len(uv_in), step,
                         max(step, vis.margin_stride)))
        if not dirs:
            return out
        hits = self.caster.cast(np.concatenate(origins), np.concatenate(dirs))
        hit = hits.valid & (hits.t <= self.reach)
        start = 0
        for ci, uv, n_in, step_in, step_out in rays:
            mine = hit[start:start + len(uv)]
            start += len(uv)
            car, inner = world.cars[ci], mine[:n_in]
            px = uv[:n_in][inner]
            visible = int(np.count_nonzero(instance_map[px[:, 1], px[:, 0]] == car.global_id))
            out[ci] = CarVisibility(car.global_id, visible * step_in ** 2,
                                    int(np.count_nonzero(inner)) * step_in ** 2,
                                    float(np.count_nonzero(mine[n_in:])) * step_out ** 2,
                                    out[ci].beyond_margin)
        return out


def _projected_rect(world: SynthWorld, car: SynthCar, i: int, world_to_cam: np.ndarray
                    ) -> tuple[np.ndarray | None, bool]:
    """Pixel-centre rectangle ``(x1, y1, x2, y2)`` that holds the car's silhouette, and whether
    part of its box lies behind the near plane.

    The rectangle of the projected mesh vertices when all are in front of the camera; otherwise
    that of the 3D box clipped at the near plane (None when nothing is in front).
    """
    cam = car.world_vertices(i) @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    g_to_cam = world_to_cam @ np.linalg.inv(WORLD_TO_G)
    box = car.box_world_g(i)
    corners_z = (box.corners() @ g_to_cam[:3, :3].T + g_to_cam[:3, 3])[:, 2]
    behind = bool(np.any(corners_z < NEAR_PLANE))
    if np.all(cam[:, 2] >= NEAR_PLANE):
        uv = project(world.rig.K, cam)
        return np.concatenate([uv.min(axis=0), uv.max(axis=0)]), behind
    return box_to_2d(box, world.rig.K, g_to_cam), behind


def _box_pixels(lo: np.ndarray, hi: np.ndarray, size: tuple[int, int], step_in: int,
                step_out: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres (u, v) of the rectangle ``[lo, hi]``: inside the image every ``step_in``-th
    and outside it every ``step_out``-th column and row (grids anchored at pixel (0, 0))."""
    w, h = size

    def grid(step: int) -> tuple[np.ndarray, np.ndarray]:
        gu = np.arange(int(np.ceil(lo[0] / step)) * step, int(hi[0]) + 1, step)
        gv = np.arange(int(np.ceil(lo[1] / step)) * step, int(hi[1]) + 1, step)
        u, v = np.meshgrid(gu, gv)
        u, v = u.ravel(), v.ravel()
        return np.column_stack([u, v]).astype(np.float64), (u >= 0) & (u < w) & (v >= 0) & (v < h)

    uv, inside = grid(step_in)
    uv_out, inside_out = grid(step_out)
    return uv[inside], uv_out[~inside_out]


def car_visibility(world: SynthWorld, i: int, instance_map: np.ndarray) -> list[CarVisibility]:
    """Occlusion and truncation of every car at frame index ``i`` (see :class:`AmodalCaster`)."""
    return AmodalCaster(world).frame(i, instance_map)


def instance_attributes(world: SynthWorld) -> dict[str, dict]:
    """The ``instances`` table of the attributes file."""
    return {str(car.global_id): {"vehicle_class": car.vehicle_class, "dynamic": bool(car.dynamic),
                                 "parking": None if car.dynamic else car.parking,
                                 "angle_to_road_deg": round(world.angle_to_road_deg(car), 3)}
            for car in world.cars}


def attributes_document(world: SynthWorld, visibility: dict[int, list[CarVisibility]]) -> dict:
    """The attributes file's content from the visibility of each frame number."""
    digits = world.config.visibility.decimals
    frames = {}
    for frame, cars in sorted(visibility.items()):
        frames[str(frame)] = {str(v.instance_value): {
            "occlusion": round(min(max(v.occluded_fraction, 0.0), 1.0), digits),
            "truncation": round(v.truncated_fraction, digits)} for v in cars if v.inside_px > 0}
    return {"format": ATTRIBUTES_FORMAT, "instances": instance_attributes(world), "frames": frames}


def write_attributes(root: str | Path, world: SynthWorld,
                     visibility: dict[int, list[CarVisibility]]) -> Path:
    """Write the attributes file of ``world`` under ``root``; returns its path."""
    path = attributes_path(root, world.sequence)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(attributes_document(world, visibility), indent=1) + "\n")
    return path


def read_attributes(path: str | Path) -> dict:
    """Read an attributes file, checking its format string and its two tables."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(path, f"cannot read the attributes file: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("format") != ATTRIBUTES_FORMAT:
        raise DataError(path, f"not a {ATTRIBUTES_FORMAT!r} file (format "
                              f"{doc.get('format') if isinstance(doc, dict) else None!r})")
    for key in ("instances", "frames"):
        if not isinstance(doc.get(key), dict):
            raise DataError(path, f"attributes file has no {key!r} table")
    return doc


__all__ = ["ATTRIBUTES_FORMAT", "AmodalCaster", "CarVisibility", "attributes_document",
           "attributes_path", "car_visibility", "instance_attributes", "read_attributes",
           "write_attributes"]
