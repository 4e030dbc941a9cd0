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
from .texture import (car_rgb, facade_rgb, kerb_rgb, lambert, prop_rgb, road_rgb, sidewalk_rgb,
                      sky_rgb, terrain_rgb)
from .world import (CAR_MATERIAL, FACADE, KERB, PROP, ROAD, SEM_SKY, SIDEWALK, TERRAIN, FrameMesh,
                    SynthWorld)


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays; arrays are per ray."""

    valid: np.ndarray  # bool
    prim: np.ndarray  # int64 face index (undefined where not valid)
    t: np.ndarray  # float64 distance along the unit direction (inf where not valid)


class RayCaster:
    """A Mitsuba scene holding one triangle mesh; casts batches of rays against it."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        m = mi.Mesh("synth", len(vertices), len(faces), has_vertex_normals=False,
                    has_vertex_texcoords=False)
        params = mi.traverse(m)
        params["vertex_positions"] = mi.Float(np.asarray(vertices).astype(np.float32).ravel())
        params["faces"] = mi.UInt32(np.asarray(faces).astype(np.uint32).ravel())
        params.update()
        self.scene = mi.load_dict({"type": "scene", "mesh": m})

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> Hits:
        """Intersect rays from ``origin`` (one (3,) point, or one per ray (N, 3)) along
        ``directions`` (N, 3); ``t`` is in units of the direction's length."""
        if len(directions) == 0:  # Dr.Jit aborts the process on empty launches
            return Hits(np.zeros(0, dtype=bool), np.zeros(0, dtype=np.int64), np.zeros(0))
        d = directions.astype(np.float32)
        o = np.asarray(origin, dtype=np.float32)
        if o.ndim == 1:
            start = mi.Point3f(float(o[0]), float(o[1]), float(o[2]))
        else:
            start = mi.Point3f(mi.Float(o[:, 0]), mi.Float(o[:, 1]), mi.Float(o[:, 2]))
        ray = mi.Ray3f(start, mi.Vector3f(mi.Float(d[:, 0]), mi.Float(d[:, 1]), mi.Float(d[:, 2])))
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
    m = mat == PROP
    if np.any(m):
        rgb = np.array([p.rgb for p in world.props], dtype=np.float64)[obj[m]]
        salt = np.array([p.salt for p in world.props], dtype=np.int64)[obj[m]]
        out[m] = prop_rgb(points[m], rgb, salt, tex)
    normals = mesh.face_normals[prim]
    cars = np.flatnonzero(mat >= CAR_MATERIAL)
    order = cars[np.argsort(obj[cars], kind="stable")]
    bounds = np.searchsorted(obj[order], np.arange(len(world.cars) + 1))
    for ci, car in enumerate(world.cars):
        m = order[bounds[ci]:bounds[ci + 1]]
        if len(m):
            local = car.to_local(points[m], i)
            lamps = car.model.lamps
            local_n = outward(normals[m] @ car.rotation(), local - car.model.box_centre) if lamps is not None else None
            out[m] = car_rgb(local, mat[m] - CAR_MATERIAL, np.asarray(car.rgb, dtype=np.float64),
                             np.full(len(m), car.salt, dtype=np.int64), tex, local_n, lamps)
    out *= lambert(normals, tex)[:, None]
    return out


def outward(normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Face normals turned to point away from the car's centre (``offsets``: the hit points from
    it): a mesh's winding need not be outward, and the lamps are painted on the faces that face
    forwards or backwards."""
    side = np.sign(np.einsum("ij,ij->i", normals, offsets))
    return normals * np.where(side == 0, 1.0, side)[:, None]


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


__all__ = ["Hits", "RayCaster", "View", "pixel_directions", "instance_values", "colours",
           "render_view"]
