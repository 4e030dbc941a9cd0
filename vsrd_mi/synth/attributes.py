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
  size beyond each border by default, every ``margin_stride``-th pixel). Where the silhouette
  reaches past the margin (a car right beside the camera, or partly behind it) the share is
  taken within the margin, a lower bound.

Cheap by construction: the cars stand apart in one "showroom" scene, each in its own frame, and
each car's rays are cast only through the pixels of its projected 3D box, all cars of a frame in
one launch.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..geometry.camera import NEAR_PLANE, box_to_2d
from .render import RayCaster
from .world import SynthWorld

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
        g_to_cam = world.g_to_camera(i, 0)
        k_inv = np.linalg.inv(K)
        stride = vis.margin_stride
        lo_lim = -np.floor(vis.margin * np.array([w, h]))
        hi_lim = np.array([w, h]) - 1 - lo_lim
        origins, dirs, owners, pixels, inside_flags = [], [], [], [], []
        meta = []
        for ci, car in enumerate(world.cars):
            box = car.box_world_g(i)
            corners_z = (box.corners() @ g_to_cam[:3, :3].T + g_to_cam[:3, 3])[:, 2]
            behind = bool(np.any(corners_z < NEAR_PLANE))
            rect = box_to_2d(box, K, g_to_cam)
            if rect is None:
                meta.append((behind, False))
                continue
            lo, hi = np.ceil(rect[:2]), np.floor(rect[2:])
            clipped = bool(np.any(lo < lo_lim) or np.any(hi > hi_lim))
            lo, hi = np.maximum(lo, lo_lim), np.minimum(hi, hi_lim)
            meta.append((behind, clipped))
            uv_in, uv_out = _box_pixels(lo, hi, (w, h), stride)
            if len(uv_in) == 0:
                continue
            uv = np.concatenate([uv_in, uv_out])
            d_cam = np.column_stack([uv, np.ones(len(uv))]) @ k_inv.T
            d_local = d_cam @ T[:3, :3].T @ car.rotation()
            d_local /= np.linalg.norm(d_local, axis=1, keepdims=True)
            o_local = car.to_local(T[:3, 3][None, :], i)[0] + self.slots[ci]
            origins.append(np.broadcast_to(o_local, d_local.shape))
            dirs.append(d_local)
            owners.append(np.full(len(uv), ci))
            pixels.append(uv.astype(np.int64))
            inside_flags.append(np.arange(len(uv)) < len(uv_in))
        out = [CarVisibility(car.global_id, 0, 0, 0.0, behind or clipped)
               for car, (behind, clipped) in zip(world.cars, meta)]
        if not dirs:
            return out
        hits = self.caster.cast(np.concatenate(origins), np.concatenate(dirs))
        hit = hits.valid & (hits.t <= self.reach)
        owner, uv, inside = np.concatenate(owners), np.concatenate(pixels), np.concatenate(inside_flags)
        for ci in np.unique(owner):
            car, sel = world.cars[ci], owner == ci
            mine_in = hit & sel & inside
            visible = int(np.count_nonzero(instance_map[uv[mine_in, 1], uv[mine_in, 0]]
                                           == car.global_id))
            outside = float(np.count_nonzero(hit & sel & ~inside)) * stride * stride
            out[ci] = CarVisibility(car.global_id, visible, int(np.count_nonzero(mine_in)),
                                    outside, out[ci].beyond_margin)
        return out


def _box_pixels(lo: np.ndarray, hi: np.ndarray, size: tuple[int, int], stride: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres (u, v) of the rectangle ``[lo, hi]`` inside the image (every pixel) and
    outside it (every ``stride``-th column and row of a grid anchored at pixel (0, 0))."""
    w, h = size
    u0, v0 = int(max(lo[0], 0)), int(max(lo[1], 0))
    u1, v1 = int(min(hi[0], w - 1)), int(min(hi[1], h - 1))
    if u1 < u0 or v1 < v0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    u, v = np.meshgrid(np.arange(u0, u1 + 1), np.arange(v0, v1 + 1))
    inside = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    gu = np.arange(int(np.ceil(lo[0] / stride)) * stride, int(hi[0]) + 1, stride)
    gv = np.arange(int(np.ceil(lo[1] / stride)) * stride, int(hi[1]) + 1, stride)
    u, v = np.meshgrid(gu, gv)
    u, v = u.ravel(), v.ravel()
    out = ~((u >= 0) & (u < w) & (v >= 0) & (v < h))
    return inside, np.column_stack([u[out], v[out]]).astype(np.float64)


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
