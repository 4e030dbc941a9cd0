"""Ray-cast rendering of the synthetic world with Mitsuba 3 (``scene.ray_intersect``).

One ray through the centre of every pixel (pixel (u, v) looks along ``K^-1 (u, v, 1)``); the
instance label of a pixel is the label of the triangle its ray hits first, so masks are exact.
Colours come from :mod:`vsrd_mi.synth.texture` at the hit point.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant)

from ..data.labels import INSTANCE_FACTOR
from ..geometry.camera import NEAR_PLANE, box_to_2d
from .texture import (car_rgb, facade_rgb, kerb_rgb, lambert, road_rgb, sidewalk_rgb, sky_rgb,
                      terrain_rgb)
from .world import (CAR_MATERIAL, FACADE, KERB, ROAD, SEM_SKY, SIDEWALK, TERRAIN, FrameMesh,
                    SynthWorld)


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays; arrays are per ray."""

    valid: np.ndarray  # bool
    prim: np.ndarray  # int64 face index (undefined where not valid)
    t: np.ndarray  # float64 distance along the unit direction (inf where not valid)


class RayCaster:
    """A Mitsuba scene holding one triangle mesh; casts batches of rays against it."""

    def __init__(self, mesh: FrameMesh):
        m = mi.Mesh("synth", len(mesh.vertices), len(mesh.faces), has_vertex_normals=False,
                    has_vertex_texcoords=False)
        params = mi.traverse(m)
        params["vertex_positions"] = mi.Float(mesh.vertices.astype(np.float32).ravel())
        params["faces"] = mi.UInt32(mesh.faces.astype(np.uint32).ravel())
        params.update()
        self.scene = mi.load_dict({"type": "scene", "mesh": m})

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> Hits:
        """Intersect rays from one ``origin`` (3,) along unit ``directions`` (N, 3)."""
        if len(directions) == 0:  # Dr.Jit aborts the process on empty launches
            return Hits(np.zeros(0, dtype=bool), np.zeros(0, dtype=np.int64), np.zeros(0))
        d = directions.astype(np.float32)
        o = np.asarray(origin, dtype=np.float32)
        ray = mi.Ray3f(mi.Point3f(float(o[0]), float(o[1]), float(o[2])),
                       mi.Vector3f(mi.Float(d[:, 0]), mi.Float(d[:, 1]), mi.Float(d[:, 2])))
        pi = self.scene.ray_intersect_preliminary(ray)
        valid_, prim_, t_ = pi.is_valid(), pi.prim_index, pi.t
        dr.eval(valid_, prim_, t_)
        valid = np.array(valid_, dtype=bool)
        prim = np.array(prim_, dtype=np.int64)
        t = np.where(valid, np.array(t_, dtype=np.float64), np.inf)
        return Hits(valid, prim, t)


def pixel_directions(K: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Camera-frame directions ``K^-1 (u, v, 1)`` through every pixel centre, row-major (H*W, 3)."""
    w, h = image_size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    return pix @ np.linalg.inv(np.asarray(K, dtype=np.float64)).T


@functools.lru_cache(maxsize=4)
def _unit_directions(k: tuple[float, ...], image_size: tuple[int, int]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Unit pixel directions and the camera-z of each (cached per camera)."""
    d = pixel_directions(np.array(k).reshape(3, 3), image_size)
    norm = np.linalg.norm(d, axis=1)
    return d / norm[:, None], 1.0 / norm


@dataclass(frozen=True)
class View:
    """A rendered view: colours, instance map and depth (camera z, inf for sky)."""

    rgb: np.ndarray  # (H, W, 3) uint8, RGB order
    instance: np.ndarray  # (H, W) uint16 KITTI-360 instance values
    depth: np.ndarray  # (H, W) float64


def instance_values(mesh: FrameMesh, hits: Hits) -> np.ndarray:
    """KITTI-360 instance-map values of the hits: ``semantic*1000 + instanceId`` for things,
    the bare semantic id for stuff, and sky where a ray hits nothing."""
    prim = np.where(hits.valid, hits.prim, 0)
    sem, inst = mesh.semantic[prim], mesh.instance[prim]
    values = np.where(inst > 0, sem * INSTANCE_FACTOR + inst, sem)
    return np.where(hits.valid, values, SEM_SKY).astype(np.uint16)


def colours(world: SynthWorld, mesh: FrameMesh, i: int, points: np.ndarray,
            prim: np.ndarray) -> np.ndarray:
    """RGB (float, 0-255) of hit ``points`` (N, 3) on faces ``prim`` at frame index ``i``."""
    tex = world.config.texture
    mat = mesh.material[prim]
    obj = mesh.obj[prim]
    out = np.zeros((len(points), 3))
    road_like = np.isin(mat, (ROAD, KERB, SIDEWALK, FACADE))
    s = np.zeros(len(points))
    n = np.zeros(len(points))
    if np.any(road_like):
        s[road_like], n[road_like] = world.centreline.to_road(points[road_like, :2])
    lane = world.config.road.lane_width
    for material, fn in ((ROAD, lambda m: road_rgb(s[m], n[m], lane, tex)),
                         (KERB, lambda m: kerb_rgb(s[m], tex)),
                         (SIDEWALK, lambda m: sidewalk_rgb(s[m], n[m], tex)),
                         (TERRAIN, lambda m: terrain_rgb(points[m, 0], points[m, 1], tex))):
        m = mat == material
        if np.any(m):
            out[m] = fn(m)
    m = mat == FACADE
    if np.any(m):
        rgb = np.array([b.rgb for b in world.buildings], dtype=np.float64)[obj[m]]
        salt = np.array([b.salt for b in world.buildings], dtype=np.int64)[obj[m]]
        out[m] = facade_rgb(s[m] + np.abs(n[m]), points[m, 2], rgb, salt, tex)
    for ci, car in enumerate(world.cars):
        m = (mat >= CAR_MATERIAL) & (obj == ci)
        if np.any(m):
            local = car.to_local(points[m], i)
            out[m] = car_rgb(local, mat[m] - CAR_MATERIAL, np.asarray(car.rgb, dtype=np.float64),
                             np.full(int(m.sum()), car.salt, dtype=np.int64), tex)
    out *= lambert(mesh.face_normals[prim], tex)[:, None]
    return out


def render_view(world: SynthWorld, mesh: FrameMesh, caster: RayCaster, i: int,
                camera: int = 0) -> View:
    """Render camera ``camera`` (0 left, 1 right) of frame index ``i``."""
    w, h = world.rig.image_size
    unit, z_per_t = _unit_directions(tuple(world.rig.K.ravel()), tuple(world.rig.image_size))
    T = world.cam_to_world(i, camera)
    dirs = unit @ T[:3, :3].T
    hits = caster.cast(T[:3, 3], dirs)
    rgb = np.empty((len(dirs), 3))
    v = hits.valid
    rgb[~v] = sky_rgb(dirs[~v], world.config.texture)
    if np.any(v):
        points = T[:3, 3] + dirs[v] * hits.t[v, None]
        rgb[v] = colours(world, mesh, i, points, hits.prim[v])
    rgb8 = np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(h, w, 3)
    depth = (hits.t * z_per_t).reshape(h, w)
    return View(rgb8, instance_values(mesh, hits).reshape(h, w), depth)




@dataclass(frozen=True)
class CarVisibility:
    """How much of a car one frame shows (left camera), from a render of the car alone."""

    instance_value: int  # pixel value in the instance map
    visible_px: int  # pixels labelled with this car in the full render
    inside_px: int  # pixels of the car alone that fall inside the image
    outside_px: int  # pixels of the car alone beyond the image borders (truncation)
    #: part of the car's box lies behind the camera's near plane, or its projection reaches more
    #: than one image size beyond the borders
    behind: bool

    @property
    def occluded_fraction(self) -> float:
        """Share of the car's in-image silhouette hidden by other geometry."""
        return 1.0 - self.visible_px / self.inside_px if self.inside_px else 1.0

    @property
    def truncated(self) -> bool:
        return self.outside_px > 0 or self.behind


def car_visibility(world: SynthWorld, i: int, instance_map: np.ndarray) -> list[CarVisibility]:
    """Occlusion and truncation of every car at frame index ``i`` given its rendered instance map.

    Each car is ray cast alone through every pixel-centre of its projected 3D box (extended beyond
    the image where the box sticks out), which contains its whole silhouette.
    """
    w, h = world.rig.image_size
    K = world.rig.K
    T = world.cam_to_world(i, 0)
    g_to_cam = world.g_to_camera(i, 0)
    out = []
    for car in world.cars:
        value = car.global_id
        visible = int(np.count_nonzero(instance_map == value))
        box = car.box_world_g(i)
        corners_z = (box.corners() @ g_to_cam[:3, :3].T + g_to_cam[:3, 3])[:, 2]
        rect = box_to_2d(box, K, g_to_cam)
        if rect is None:
            out.append(CarVisibility(value, visible, 0, 0, bool(np.any(corners_z < NEAR_PLANE))))
            continue
        lo = np.floor(rect[:2]).astype(int) - 1
        hi = np.ceil(rect[2:]).astype(int) + 1
        # cars right beside the camera project to huge boxes: render at most one image size
        # beyond each border and count such a car as truncated
        size = np.array([w, h])
        clipped = bool(np.any(lo < -size) or np.any(hi > 2 * size - 1))
        (u0, v0), (u1, v1) = np.maximum(lo, -size), np.minimum(hi, 2 * size - 1)
        u, v = np.meshgrid(np.arange(u0, u1 + 1, dtype=np.float64),
                           np.arange(v0, v1 + 1, dtype=np.float64))
        pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ np.linalg.inv(K).T
        dirs = pix / np.linalg.norm(pix, axis=1, keepdims=True) @ T[:3, :3].T
        hits = RayCaster(world.frame_mesh(i, cars=[car], with_static=False)).cast(T[:3, 3], dirs)
        inside = (u.ravel() >= 0) & (u.ravel() < w) & (v.ravel() >= 0) & (v.ravel() < h)
        out.append(CarVisibility(value, visible, int(np.count_nonzero(hits.valid & inside)),
                                 int(np.count_nonzero(hits.valid & ~inside)),
                                 bool(np.any(corners_z < NEAR_PLANE)) or clipped))
    return out


__all__ = ["Hits", "RayCaster", "View", "CarVisibility", "pixel_directions", "instance_values",
           "colours", "render_view", "car_visibility"]
