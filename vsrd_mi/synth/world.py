"""The 3D world of a synthetic KITTI-360 sequence: street, buildings, cars and the ego rig.

World frame: z up, metres, the road surface at z = 0. The street follows a gently curving centre
line; the ego drives in the right-hand lane. Parked cars stand in parking strips on both sides,
moving cars drive in straight lines at constant velocity (metres per frame index) in the ego lane
ahead of the ego or in the oncoming lane. Everything is decided by :func:`build_world` from a
seed, so the same arguments give the same world.

A car's ground-truth box is the tight box of its placed mesh. In KITTI-360 terms its
``transform`` is ``[R_z(yaw) @ diag(length, width, height) | centre]`` (local x = heading,
y = left, z = up); in a camera frame it is a :class:`~vsrd_mi.geometry.boxes.Box3D` obtained by
:meth:`SynthWorld.boxes_in_camera`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from shapely.geometry import Polygon

from ..data.kitti360 import sequence_name
from ..data.labels import CAR_LABEL_ID, INSTANCE_FACTOR, car_instance_value
from ..data.observations import rotation_x
from ..geometry.boxes import Box3D, yaw_matrix
from .cars import CarModel, bundled_mesh_paths, load_car_mesh, procedural_car, scaled
from .config import RoadConfig, SynthConfig

# Materials of the world mesh faces (car materials are CAR_MATERIAL + cars.BODY/GLASS/TYRE).
ROAD, KERB, SIDEWALK, TERRAIN, FACADE = 0, 1, 2, 3, 4
CAR_MATERIAL = 10

# KITTI-360 / Cityscapes semantic ids written into the instance maps (stuff as bare ids).
SEM_ROAD, SEM_SIDEWALK, SEM_BUILDING, SEM_TERRAIN, SEM_SKY = 7, 8, 11, 22, 23

#: Spacing of the dense centre-line samples (interpolated linearly), metres.
CENTRELINE_RESOLUTION = 0.05
#: Newton steps of :meth:`Centreline.to_road`.
TO_ROAD_NEWTON_STEPS = 3

#: Gravity-aligned y-down frame G = (x_w, -z_w, y_w): lets world boxes be :class:`Box3D` values.
WORLD_TO_G = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def homogeneous(R: np.ndarray, t: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


class Centreline:
    """The road's centre line: heading ``psi(s)`` with sinusoidal curvature, integrated densely."""

    def __init__(self, s_min: float, s_max: float, heading0: float, curvature: float,
                 wavelength: float, phase: float):
        self.s = np.arange(s_min, s_max + CENTRELINE_RESOLUTION, CENTRELINE_RESOLUTION)
        k = 2.0 * np.pi / wavelength
        # psi(s) = heading0 + int_0^s curvature * sin(k u + phase) du
        self.psi = heading0 + curvature / k * (np.cos(phase) - np.cos(k * self.s + phase))
        direction = np.stack([np.cos(self.psi), np.sin(self.psi)], axis=1)
        steps = 0.5 * (direction[1:] + direction[:-1]) * np.diff(self.s)[:, None]
        xy = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])
        self.xy = xy - np.array([np.interp(0.0, self.s, xy[:, 0]), np.interp(0.0, self.s, xy[:, 1])])

    def point(self, s: np.ndarray | float) -> np.ndarray:
        return np.stack([np.interp(s, self.s, self.xy[:, 0]),
                         np.interp(s, self.s, self.xy[:, 1])], axis=-1)

    def heading(self, s: np.ndarray | float) -> np.ndarray:
        return np.interp(s, self.s, self.psi)

    def left(self, s: np.ndarray | float) -> np.ndarray:
        psi = self.heading(s)
        return np.stack([-np.sin(psi), np.cos(psi)], axis=-1)

    def at(self, s: np.ndarray | float, n: np.ndarray | float) -> np.ndarray:
        """World xy of road coordinates (s along, n to the left)."""
        return self.point(s) + np.asarray(n)[..., None] * self.left(s)

    def to_road(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates ``(s, n)`` of world points ``xy`` (N, 2).

        Newton steps on ``s`` from the projection onto the initial tangent; the centre line is
        gently curved (|curvature * n| << 1 within the modelled street), so a fixed number of
        steps converges to float precision.
        """
        xy = np.asarray(xy, dtype=np.float64)
        psi0 = self.psi[np.searchsorted(self.s, 0.0)]
        s = (xy - self.point(0.0)) @ np.array([np.cos(psi0), np.sin(psi0)])
        for _ in range(TO_ROAD_NEWTON_STEPS):
            psi = self.heading(s)
            d = xy - self.point(s)
            s = s + d[:, 0] * np.cos(psi) + d[:, 1] * np.sin(psi)
        psi = self.heading(s)
        d = xy - self.point(s)
        return s, -d[:, 0] * np.sin(psi) + d[:, 1] * np.cos(psi)


@dataclass
class MeshParts:
    """Triangle soup with per-face material, semantic id, instance id and object index.

    Each part keeps its own vertex indexing; :meth:`build` offsets them into one mesh.
    """

    vertices: list[np.ndarray] = field(default_factory=list)
    faces: list[np.ndarray] = field(default_factory=list)
    material: list[np.ndarray] = field(default_factory=list)
    semantic: list[np.ndarray] = field(default_factory=list)
    instance: list[np.ndarray] = field(default_factory=list)
    obj: list[np.ndarray] = field(default_factory=list)

    def add(self, verts: np.ndarray, faces: np.ndarray, material: np.ndarray | int,
            semantic: int, instance: int = 0, obj: int = -1) -> None:
        nf = len(faces)
        self.vertices.append(np.asarray(verts, dtype=np.float64))
        self.faces.append(np.asarray(faces, dtype=np.int64))
        self.material.append(np.broadcast_to(np.asarray(material, dtype=np.int16), (nf,)).copy())
        self.semantic.append(np.full(nf, semantic, dtype=np.int32))
        self.instance.append(np.full(nf, instance, dtype=np.int32))
        self.obj.append(np.full(nf, obj, dtype=np.int32))

    def extend(self, other: "MeshParts") -> None:
        for name in ("vertices", "faces", "material", "semantic", "instance", "obj"):
            getattr(self, name).extend(getattr(other, name))

    def build(self) -> "FrameMesh":
        offsets = np.cumsum([0] + [len(v) for v in self.vertices[:-1]])
        faces = np.concatenate([f + o for f, o in zip(self.faces, offsets)])
        return FrameMesh(np.concatenate(self.vertices), faces, np.concatenate(self.material),
                         np.concatenate(self.semantic), np.concatenate(self.instance),
                         np.concatenate(self.obj))


@dataclass(frozen=True)
class FrameMesh:
    """One merged triangle mesh of everything in the world at one frame."""

    vertices: np.ndarray  # (V, 3) world
    faces: np.ndarray  # (F, 3)
    material: np.ndarray  # (F,)
    semantic: np.ndarray  # (F,) semantic id
    instance: np.ndarray  # (F,) instanceId (0 for stuff)
    obj: np.ndarray  # (F,) building index or car index (-1 for none)

    @property
    def face_normals(self) -> np.ndarray:
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.maximum(norm, 1e-12)


def _ribbon(cl: Centreline, s: np.ndarray, a: tuple[float, float],
            b: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Quad strip along the road between cross-section points a=(n, z) and b=(n, z)."""
    pa = np.column_stack([cl.at(s, np.full_like(s, a[0])), np.full_like(s, a[1])])
    pb = np.column_stack([cl.at(s, np.full_like(s, b[0])), np.full_like(s, b[1])])
    verts = np.empty((2 * len(s), 3))
    verts[0::2], verts[1::2] = pa, pb
    j = np.arange(len(s) - 1) * 2
    faces = np.concatenate([np.stack([j, j + 2, j + 1], 1), np.stack([j + 1, j + 2, j + 3], 1)])
    return verts, faces


def _quad(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles of the quad with corners p[0..3] in order."""
    return np.asarray(p, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]])


@dataclass(frozen=True)
class Building:
    """A facade block along one side of the street (for its texture)."""

    side: int
    s0: float
    s1: float
    offset: float  # lateral distance of the facade from the centre line
    height: float
    rgb: tuple[int, int, int]
    salt: int


def _sample_s(lo: float, hi: float, step: float) -> np.ndarray:
    n = max(int(np.ceil((hi - lo) / step)), 1)
    return np.linspace(lo, hi, n + 1)


def build_static(cl: Centreline, road: RoadConfig, rng: np.random.Generator
                 ) -> tuple[MeshParts, list[Building]]:
    """Road, kerbs, sidewalks, terrain and building facades along the whole centre line."""
    parts = MeshParts()
    s = _sample_s(cl.s[0], cl.s[-1], road.mesh_step)
    edge = road.lane_width + road.parking_width
    walk = edge + road.sidewalk_width
    parts.add(*_ribbon(cl, s, (-edge, 0.0), (edge, 0.0)), ROAD, SEM_ROAD)
    buildings: list[Building] = []
    for side in (-1.0, 1.0):
        parts.add(*_ribbon(cl, s, (side * edge, 0.0), (side * edge, road.kerb_height)),
                  KERB, SEM_SIDEWALK)
        parts.add(*_ribbon(cl, s, (side * edge, road.kerb_height), (side * walk, road.kerb_height)),
                  SIDEWALK, SEM_SIDEWALK)
        parts.add(*_ribbon(cl, s, (side * walk, road.kerb_height), (side * walk, 0.0)),
                  SIDEWALK, SEM_SIDEWALK)
        parts.add(*_ribbon(cl, s, (side * walk, 0.0), (side * road.back_wall_offset, 0.0)),
                  TERRAIN, SEM_TERRAIN)
        back = Building(int(side), float(s[0]), float(s[-1]), road.back_wall_offset,
                        float(road.building_height[1]), _building_rgb(rng, road),
                        int(rng.integers(1 << 30)))
        parts.add(*_ribbon(cl, s, (side * back.offset, 0.0), (side * back.offset, back.height)),
                  FACADE, SEM_BUILDING, obj=len(buildings))
        buildings.append(back)
        pos = float(s[0]) + float(rng.uniform(0.0, road.building_length[1]))
        while pos < s[-1]:
            length = float(rng.uniform(*road.building_length))
            s1 = min(pos + length, float(s[-1]))
            b = Building(int(side), pos, s1, walk + float(rng.uniform(*road.building_setback)),
                         float(rng.uniform(*road.building_height)), _building_rgb(rng, road),
                         int(rng.integers(1 << 30)))
            idx = len(buildings)
            buildings.append(b)
            sb = _sample_s(b.s0, b.s1, road.mesh_step)
            parts.add(*_ribbon(cl, sb, (side * b.offset, 0.0), (side * b.offset, b.height)),
                      FACADE, SEM_BUILDING, obj=idx)
            for se in (b.s0, b.s1):  # end walls, visible through gaps
                inner = cl.at(se, side * b.offset)
                outer = cl.at(se, side * (b.offset + road.building_depth))
                parts.add(*_quad([[*inner, 0.0], [*outer, 0.0], [*outer, b.height],
                                  [*inner, b.height]]), FACADE, SEM_BUILDING, obj=idx)
            pos = s1
            if rng.uniform() < road.building_gap_prob:
                pos += float(rng.uniform(*road.building_gap))
    return parts, buildings


def _building_rgb(rng: np.random.Generator, road: RoadConfig) -> tuple[int, int, int]:
    base = rng.uniform(*road.building_grey)
    tint = rng.uniform(-road.building_tint, road.building_tint, size=3)
    return tuple(int(np.clip(base + t, 0, 255)) for t in tint)


@dataclass(frozen=True)
class SynthCar:
    """A placed car: model, paint, world yaw, centre at the first frame and velocity per frame."""

    instance_id: int  # the XML instanceId; its pixels hold car_instance_value(instance_id)
    model: CarModel
    dynamic: bool
    yaw: float  # world yaw of the heading about +z
    centre0: np.ndarray  # world centre of the tight box at frame index 0 of the sequence
    velocity: np.ndarray  # world metres per frame index (zero for parked cars)
    rgb: tuple[int, int, int]
    salt: int

    @property
    def size_lwh(self) -> np.ndarray:
        return self.model.size

    @property
    def global_id(self) -> int:
        """Instance-map pixel value ``26 * 1000 + instance_id``."""
        return car_instance_value(self.instance_id)

    def centre(self, i: int) -> np.ndarray:
        """World box centre at frame index ``i`` (0 = first frame of the sequence)."""
        return self.centre0 + self.velocity * i

    def rotation(self) -> np.ndarray:
        return rot_z(self.yaw)

    def world_vertices(self, i: int) -> np.ndarray:
        return (self.model.vertices - self.model.box_centre) @ self.rotation().T + self.centre(i)

    def to_local(self, pts: np.ndarray, i: int) -> np.ndarray:
        """World points -> the car model's frame (x fwd, y left, z up, model coordinates)."""
        return (pts - self.centre(i)) @ self.rotation() + self.model.box_centre

    def box_world_g(self, i: int) -> Box3D:
        """The box in the gravity-aligned y-down frame :data:`WORLD_TO_G` (exact, not tilted)."""
        l, w, h = self.size_lwh
        c = WORLD_TO_G[:3, :3] @ self.centre(i)
        heading = WORLD_TO_G[:3, :3] @ self.rotation()[:, 0]
        return Box3D(centre=c, size=(w, h, l), yaw=float(np.arctan2(heading[0], heading[2])),
                     velocity=WORLD_TO_G[:3, :3] @ self.velocity, dynamic=self.dynamic,
                     instance_id=self.global_id)

    def footprint(self, i: int, pad: float = 0.0) -> Polygon:
        l, w, _ = self.size_lwh
        hl, hw = 0.5 * l + pad, 0.5 * w + pad
        R = self.rotation()[:2, :2]
        corners = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]]) @ R.T + self.centre(i)[:2]
        return Polygon(corners)


@dataclass(frozen=True)
class Rig:
    """Calibration of the stereo rig (see :class:`~vsrd_mi.synth.config.RigConfig`)."""

    K: np.ndarray  # 3x3
    baseline: float
    r_rect_00: np.ndarray  # 3x3
    cam0_to_pose: np.ndarray  # 4x4, unrectified cam0 -> IMU
    image_size: tuple[int, int]


@dataclass
class SynthWorld:
    """Everything about a synthetic sequence except its pixels."""

    config: SynthConfig
    sequence: str
    frames: list[int]
    rig: Rig
    centreline: Centreline
    static: MeshParts
    buildings: list[Building]
    cars: list[SynthCar]
    poses: list[np.ndarray]  # IMU -> world, 4x4 per frame index
    cam0_to_world: list[np.ndarray]  # rectified cam0 -> world, 4x4 per frame index

    def cam_to_world(self, i: int, camera: int = 0) -> np.ndarray:
        """Rectified camera ``camera`` (0 left, 1 right) -> world at frame index ``i``."""
        T = self.cam0_to_world[i]
        if camera == 1:
            T = T @ homogeneous(np.eye(3), (self.rig.baseline, 0.0, 0.0))
        return T

    def frame_mesh(self, i: int, cars: Sequence[SynthCar] | None = None,
                   with_static: bool = True) -> FrameMesh:
        """All geometry at frame index ``i`` (``cars`` defaults to every car)."""
        parts = MeshParts()
        if with_static:
            parts.extend(self.static)
        for car in (self.cars if cars is None else cars):
            parts.add(car.world_vertices(i), car.model.faces,
                      CAR_MATERIAL + car.model.materials.astype(np.int16), CAR_LABEL_ID,
                      car.instance_id, self.cars.index(car))
        return parts.build()

    def boxes_in_camera(self, i: int) -> list[Box3D]:
        """Ground-truth boxes of every car in the rectified cam0 frame of frame index ``i``.

        Centre and velocity are transformed exactly; the yaw is that of the heading projected to
        the camera's x-z plane (the camera is pitched, so the box is not exactly y-aligned there).
        """
        world_to_cam = np.linalg.inv(self.cam0_to_world[i])
        g_to_cam = world_to_cam @ np.linalg.inv(WORLD_TO_G)
        return [car.box_world_g(i).transformed(g_to_cam) for car in self.cars]

    def g_to_camera(self, i: int, camera: int = 0) -> np.ndarray:
        """4x4 map from the y-down world frame of :meth:`SynthCar.box_world_g` to camera ``camera``."""
        return np.linalg.inv(self.cam_to_world(i, camera)) @ np.linalg.inv(WORLD_TO_G)


def _smooth_noise(rng: np.random.Generator, n: int, amplitude: float, period: tuple[float, float],
                  terms: int) -> np.ndarray:
    """Sum of ``terms`` random sinusoids over ``n`` frames, peak amplitude at most ``amplitude``."""
    k = np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for _ in range(terms):
        out += np.sin(2 * np.pi * k / rng.uniform(*period) + rng.uniform(0, 2 * np.pi))
    return amplitude * out / terms


def _ego_track(config: SynthConfig, n: int, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame ego arc length, lateral jitter, yaw, pitch and roll noise."""
    ego = config.ego
    steps = ego.step + _smooth_noise(rng, n, ego.step_jitter, ego.noise_period, ego.noise_terms)
    s = np.concatenate([[0.0], np.cumsum(steps[:-1])])
    lateral = _smooth_noise(rng, n, ego.lateral_jitter, ego.noise_period, ego.noise_terms)
    yaw, pitch, roll = (np.deg2rad(_smooth_noise(rng, n, a, ego.noise_period, ego.noise_terms))
                        for a in (ego.yaw_noise_deg, ego.pitch_noise_deg, ego.roll_noise_deg))
    return s, lateral, yaw, pitch, roll


#: IMU frame (x forward, y right, z down) relative to a vehicle frame (x forward, y left, z up).
FLU_TO_FRD = np.diag([1.0, -1.0, -1.0])


def _ego_poses(config: SynthConfig, rig: Rig, cl: Centreline, track: tuple[np.ndarray, ...]
               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """IMU -> world poses and rectified cam0 -> world per frame; the camera centre sits
    ``camera_height`` above the lane (with lateral jitter)."""
    s, lateral, dyaw, pitch, roll = track
    lane_n = -0.5 * config.road.lane_width
    rr_inv = np.linalg.inv(homogeneous(rig.r_rect_00))  # R_rect_00 is orthonormal to ~1e-6 only
    poses, cams = [], []
    for k in range(len(s)):
        # vehicle yaw about z, then pitch about y and roll about x, then the IMU's axis flip
        R_imu = (rot_z(float(cl.heading(s[k])) + dyaw[k]) @ yaw_matrix(pitch[k])
                 @ rotation_x(roll[k]) @ FLU_TO_FRD)
        cam_xy = cl.at(s[k], lane_n + lateral[k])
        cam_centre = np.array([cam_xy[0], cam_xy[1], config.rig.camera_height])
        pose = homogeneous(R_imu, cam_centre - R_imu @ rig.cam0_to_pose[:3, 3])
        poses.append(pose)
        cams.append(pose @ rig.cam0_to_pose @ rr_inv)
    return poses, cams


def make_rig(config: SynthConfig) -> Rig:
    r = config.rig
    K = np.array([[r.fx, 0.0, r.cx], [0.0, r.fy, r.cy], [0.0, 0.0, 1.0]])
    c2p = np.eye(4)
    c2p[:3, :] = np.asarray(r.cam0_to_pose, dtype=np.float64).reshape(3, 4)
    return Rig(K, r.baseline, np.asarray(r.r_rect_00, dtype=np.float64).reshape(3, 3), c2p,
               r.image_size)


class PlacementError(ValueError):
    """The requested cars do not fit in the street (too many for its length)."""


def _collides(candidate: SynthCar, placed: Sequence[SynthCar], n_frames: int, gap: float) -> bool:
    moving = candidate.dynamic or any(c.dynamic for c in placed)
    frames = range(n_frames) if moving else range(1)
    for i in frames:
        fp = candidate.footprint(i, pad=0.5 * gap)
        for other in placed:
            if (candidate.dynamic or other.dynamic or i == 0) and \
                    fp.intersects(other.footprint(i, pad=0.5 * gap)):
                return True
    return False


def _pick_model(rng: np.random.Generator, config: SynthConfig,
                meshes: Sequence[CarModel]) -> CarModel:
    if not meshes or rng.uniform() < config.traffic.procedural_fraction:
        return procedural_car(rng, config.procedural)
    model = meshes[int(rng.integers(len(meshes)))]
    j = config.traffic.mesh_scale_jitter
    return scaled(model, 1.0 + float(rng.uniform(-j, j)))


def _paint(rng: np.random.Generator, config: SynthConfig) -> tuple[int, int, int]:
    pal = config.texture.car_palette
    return pal[int(rng.integers(len(pal)))]


def _place_dynamic(rng: np.random.Generator, config: SynthConfig, cl: Centreline,
                   ego_s: np.ndarray, model: CarModel, instance_id: int) -> SynthCar:
    """A car driving straight at constant speed along the chord of its lane (ego lane ahead of
    the ego, or the oncoming lane passing the ego)."""
    tr, n = config.traffic, len(ego_s)
    v = float(rng.uniform(*tr.speed)) / config.rig.frame_rate
    length = float(model.size[0])
    k = np.arange(n)
    if rng.uniform() < tr.same_direction_prob:
        lane, sign = -0.5 * config.road.lane_width, 1.0
        s0 = float(np.max(ego_s - v * k)) + tr.follow_gap + 0.5 * length + rng.uniform(*tr.follow_extra)
    else:
        lane, sign = 0.5 * config.road.lane_width, -1.0
        kp = rng.uniform(*tr.oncoming_pass) * n
        s0 = float(np.interp(kp, k, ego_s, right=ego_s[-1] + config.ego.step * (kp - n + 1))) + v * kp
    s_end = s0 + sign * v * max(n - 1, 1)
    a, b = cl.at(s0, lane), cl.at(s_end, lane)
    vel_xy = (b - a) / max(n - 1, 1)
    yaw = float(np.arctan2(vel_xy[1], vel_xy[0]))
    centre0 = np.array([a[0], a[1], 0.5 * model.size[2]])
    return SynthCar(instance_id, model, True, yaw, centre0, np.array([vel_xy[0], vel_xy[1], 0.0]),
                    _paint(rng, config), int(rng.integers(1 << 30)))


def _place_parked(rng: np.random.Generator, config: SynthConfig, cl: Centreline,
                  ego_s: np.ndarray, model: CarModel, instance_id: int) -> SynthCar | None:
    """A parked car in a parking strip (None when its rotated footprint does not fit)."""
    tr, road = config.traffic, config.road
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    s = float(rng.uniform(ego_s[0] + tr.parked_range[0], ego_s[-1] + tr.parked_range[1]))
    rel = np.deg2rad(rng.normal(0.0, tr.parked_yaw_jitter_deg))
    if rng.uniform() < tr.angled_prob:
        rel += np.deg2rad(rng.uniform(*tr.angled_yaw_deg)) * (1.0 if rng.uniform() < 0.5 else -1.0)
    if rng.uniform() < tr.parked_reverse_prob:
        rel += np.pi
    # lateral half-extent of the rotated footprint, across the road
    l, w = float(model.size[0]), float(model.size[1])
    half_across = 0.5 * (l * abs(np.sin(rel)) + w * abs(np.cos(rel)))
    inner = road.lane_width - tr.lane_intrusion + half_across
    outer = road.lane_width + road.parking_width - tr.kerb_clearance - half_across
    if inner > outer:
        return None
    mid = road.lane_width + 0.5 * road.parking_width + rng.uniform(-1, 1) * tr.parked_lateral_jitter
    n = side * float(np.clip(mid, inner, outer))
    xy = cl.at(s, n)
    yaw = float(cl.heading(s)) + rel
    return SynthCar(instance_id, model, False, yaw, np.array([xy[0], xy[1], 0.5 * model.size[2]]),
                    np.zeros(3), _paint(rng, config), int(rng.integers(1 << 30)))


def build_world(seq: int = 0, frames: int = 60, n_static: int = 4, n_dynamic: int = 2,
                seed: int = 0, meshes: Sequence[str | Path] | None = None,
                config: SynthConfig = SynthConfig()) -> SynthWorld:
    """Lay out a synthetic sequence (deterministic in all arguments).

    ``meshes``: car mesh files (None: the bundled CC0 meshes; empty: procedural cars only).
    Raises :class:`PlacementError` when the cars cannot be placed without collisions and
    :class:`~vsrd_mi.errors.DataError` for unreadable mesh files.
    """
    if frames < 1 or n_static < 0 or n_dynamic < 0 or seq < 0:
        raise ValueError(f"need frames >= 1, seq >= 0 and non-negative car counts "
                         f"(got frames={frames}, seq={seq}, static={n_static}, dynamic={n_dynamic})")
    if n_static + n_dynamic >= INSTANCE_FACTOR:
        raise ValueError(f"at most {INSTANCE_FACTOR - 1} cars fit the KITTI-360 instance encoding")
    rng = np.random.default_rng([seed, seq])
    models = [load_car_mesh(p) for p in (bundled_mesh_paths() if meshes is None else meshes)]
    rig = make_rig(config)
    track = _ego_track(config, frames, rng)
    ego_s = track[0]
    road = config.road
    cl = Centreline(ego_s[0] - road.behind, ego_s[-1] + road.ahead,
                    heading0=float(rng.uniform(-np.pi, np.pi)),
                    curvature=float(rng.uniform(-1, 1)) * road.max_curvature,
                    wavelength=float(rng.uniform(*road.curvature_wavelength)),
                    phase=float(rng.uniform(0, 2 * np.pi)))
    static, buildings = build_static(cl, road, rng)
    poses, cams = _ego_poses(config, rig, cl, track)

    cars: list[SynthCar] = []
    for kind, count in (("dynamic", n_dynamic), ("parked", n_static)):
        for _ in range(count):
            for _try in range(config.traffic.max_tries):
                model = _pick_model(rng, config, models)
                place = _place_dynamic if kind == "dynamic" else _place_parked
                car = place(rng, config, cl, ego_s, model, len(cars) + 1)
                if car is not None and not _collides(car, cars, frames, config.traffic.min_gap):
                    cars.append(car)
                    break
            else:
                raise PlacementError(
                    f"could not place {kind} car {len(cars) + 1} without collisions after "
                    f"{config.traffic.max_tries} tries: ask for fewer cars or more frames")
    frame_ids = [config.first_frame + i for i in range(frames)]
    return SynthWorld(config, sequence_name(seq), frame_ids, rig, cl, static, buildings, cars,
                      poses, cams)
