"""The 3D world of a synthetic KITTI-360 sequence: street, buildings, cars and the ego rig.

World frame: z up, metres, the road surface at z = 0. The street follows a gently curving centre
line; the ego drives in the right-hand lane. Parked cars stand in parking strips on both sides,
moving cars drive in straight lines at constant velocity (metres per frame index) in the ego lane
ahead of the ego or in the oncoming lane. Props (poles, signs, trees, pedestrians, bins) may stand
on the sidewalks and between parked cars. Everything is decided by
:func:`vsrd_mi.synth.layout.build_world` from a seed, so the same arguments give the same world.

A car's ground-truth box is the tight box of its placed mesh. In KITTI-360 terms its
``transform`` is ``[R_z(yaw) @ diag(length, width, height) | centre]`` (local x = heading,
y = left, z = up); in a camera frame it is a :class:`~vsrd_mi.geometry.boxes.Box3D` obtained by
:meth:`SynthWorld.boxes_in_camera`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from shapely.geometry import Polygon

from ..data.labels import CAR_LABEL_ID, car_instance_value
from ..data.observations import rotation_x
from ..geometry.boxes import Box3D, yaw_matrix
from .cars import CarModel
from .config import RoadConfig, SynthConfig

# Materials of the world mesh faces (car materials are CAR_MATERIAL + cars.BODY/GLASS/TYRE/RIM;
# a PROP face's colour is that of the prop part its object index names).
ROAD, KERB, SIDEWALK, TERRAIN, FACADE, PROP = 0, 1, 2, 3, 4, 5
CAR_MATERIAL = 10

# KITTI-360 / Cityscapes semantic ids written into the instance maps (stuff as bare ids).
SEM_ROAD, SEM_SIDEWALK, SEM_BUILDING, SEM_TERRAIN, SEM_SKY = 7, 8, 11, 22, 23
# ... and those of the props: poles, traffic signs and persons carry instance ids like cars
# (semantic * 1000 + instance), vegetation is stuff, trash bins are things.
SEM_POLE, SEM_TRAFFIC_SIGN, SEM_VEGETATION, SEM_PERSON, SEM_TRASH_BIN = 17, 20, 21, 24, 39

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


def road_edges(road: RoadConfig, parking_widths: tuple[float, float] | None = None
               ) -> tuple[float, float]:
    """Distances of the right (-n) and left (+n) kerbs from the centre line: the lane plus the
    parking strip of that side (``parking_widths`` = (right, left); default the config's)."""
    right, left = (road.parking_width,) * 2 if parking_widths is None else parking_widths
    return road.lane_width + right, road.lane_width + left


def build_static(cl: Centreline, road: RoadConfig, rng: np.random.Generator,
                 parking_widths: tuple[float, float] | None = None
                 ) -> tuple[MeshParts, list[Building]]:
    """Road, kerbs, sidewalks, terrain and building facades along the whole centre line.

    ``parking_widths`` = (right, left) parking strip widths (default: ``road.parking_width``).
    """
    parts = MeshParts()
    s = _sample_s(cl.s[0], cl.s[-1], road.mesh_step)
    edges = road_edges(road, parking_widths)
    parts.add(*_ribbon(cl, s, (-edges[0], 0.0), (edges[1], 0.0)), ROAD, SEM_ROAD)
    buildings: list[Building] = []
    for side, edge in zip((-1.0, 1.0), edges):
        walk = edge + road.sidewalk_width
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
    #: How a parked car stands: "parallel" (facing its side's traffic direction),
    #: "parallel_reversed", "angled" or "perpendicular"; None for moving cars.
    parking: str | None = None

    @property
    def size_lwh(self) -> np.ndarray:
        return self.model.size

    @property
    def vehicle_class(self) -> str:
        return self.model.vehicle_class or self.model.name

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
class PropPart:
    """One coloured part of a prop (a pole, a sign's plate, a pedestrian's torso, ...)."""

    kind: str
    rgb: tuple[int, int, int]
    salt: int


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
    #: Parts of the props (their faces are in ``static`` with material PROP, obj = part index).
    props: list["PropPart"] = field(default_factory=list)
    #: Per-sequence camera (pitch, roll) in degrees drawn from the rig config (None: not drawn).
    camera_attitude: tuple[float, float] | None = None
    #: Parking layout of each side: (side, s0, s1, layout, angle deg), side -1 right / +1 left.
    parking_segments: list[tuple[int, float, float, str, float]] = field(default_factory=list)

    def angle_to_road_deg(self, car: SynthCar) -> float:
        """Angle between the car's length axis and the road direction at its centre (0..90 deg)."""
        s, _ = self.centreline.to_road(car.centre(0)[None, :2])
        a = abs(float(np.degrees(car.yaw - self.centreline.heading(s[0])))) % 180.0
        return min(a, 180.0 - a)

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


def ego_track(config: SynthConfig, n: int, rng: np.random.Generator
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


def ego_poses(config: SynthConfig, rig: Rig, cl: Centreline, track: tuple[np.ndarray, ...],
               attitude: tuple[float, float] = (0.0, 0.0)
               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """IMU -> world poses and rectified cam0 -> world per frame; the camera centre sits
    ``camera_height`` above the lane (with lateral jitter). ``attitude`` = (pitch, roll) in
    radians is added to the vehicle's pitch and roll noise at every frame."""
    s, lateral, dyaw, pitch, roll = track
    if attitude != (0.0, 0.0):
        pitch, roll = pitch + attitude[0], roll + attitude[1]
    lane_n = -0.5 * config.road.lane_width
    poses, cams = [], []
    for k in range(len(s)):
        cam_xy = cl.at(s[k], lane_n + lateral[k])
        pose, cam = vehicle_pose(rig, float(cl.heading(s[k])) + dyaw[k], pitch[k], roll[k],
                                 np.array([cam_xy[0], cam_xy[1], config.rig.camera_height]))
        poses.append(pose)
        cams.append(cam)
    return poses, cams


def vehicle_pose(rig: Rig, yaw: float, pitch: float, roll: float, cam_centre: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """IMU -> world pose and rectified cam0 -> world of a vehicle with this yaw, pitch (nose down
    positive) and roll (about its forward axis, radians) whose left camera centre is at
    ``cam_centre``."""
    # vehicle yaw about z, then pitch about y and roll about x, then the IMU's axis flip
    R_imu = rot_z(yaw) @ yaw_matrix(pitch) @ rotation_x(roll) @ FLU_TO_FRD
    pose = homogeneous(R_imu, cam_centre - R_imu @ rig.cam0_to_pose[:3, 3])
    rr_inv = np.linalg.inv(homogeneous(rig.r_rect_00))  # R_rect_00 is orthonormal to ~1e-6 only
    return pose, pose @ rig.cam0_to_pose @ rr_inv


def camera_pitch_roll(cam_to_world: np.ndarray) -> tuple[float, float]:
    """``(pitch, roll)`` of a camera in degrees relative to the z-up world.

    Pitch: how far the optical axis (camera +z) points below the horizon. Roll: how far the
    camera's +x axis (image right) points above the horizon (KITTI-360's left camera: pitch about
    5.8-6.1 deg, roll about -0.9 deg by this measure).
    """
    R = np.asarray(cam_to_world, dtype=np.float64)[:3, :3]
    return (float(np.degrees(np.arcsin(-R[2, 2]))), float(np.degrees(np.arcsin(R[2, 0]))))


#: Newton steps of :func:`vehicle_attitude_for` (the map is nearly the identity: 3 reach 1e-12 deg).
ATTITUDE_NEWTON_STEPS = 4
#: Finite-difference step of its Jacobian, radians.
ATTITUDE_FD_STEP = 1e-6


def vehicle_attitude_for(rig: Rig, pitch_deg: float, roll_deg: float) -> tuple[float, float]:
    """Vehicle (pitch, roll) in radians that give the left camera this :func:`camera_pitch_roll`
    when the vehicle's noise is zero (the camera's mounting comes from the calibration)."""
    target = np.array([pitch_deg, roll_deg])

    def measure(x: np.ndarray) -> np.ndarray:
        return np.array(camera_pitch_roll(vehicle_pose(rig, 0.0, x[0], x[1], np.zeros(3))[1]))

    x = np.zeros(2)
    for _ in range(ATTITUDE_NEWTON_STEPS):
        f = measure(x)
        J = np.stack([(measure(x + ATTITUDE_FD_STEP * e) - f) / ATTITUDE_FD_STEP
                      for e in np.eye(2)], axis=1)
        x = x + np.linalg.solve(J, target - f)
    return float(x[0]), float(x[1])


def make_rig(config: SynthConfig) -> Rig:
    r = config.rig
    K = np.array([[r.fx, 0.0, r.cx], [0.0, r.fy, r.cy], [0.0, 0.0, 1.0]])
    c2p = np.eye(4)
    c2p[:3, :] = np.asarray(r.cam0_to_pose, dtype=np.float64).reshape(3, 4)
    return Rig(K, r.baseline, np.asarray(r.r_rect_00, dtype=np.float64).reshape(3, 3), c2p,
               r.image_size)


class PlacementError(ValueError):
    """The requested cars do not fit in the street (too many for its length)."""


def collides(candidate: SynthCar, placed: Sequence[SynthCar], n_frames: int, gap: float) -> bool:
    """Whether the candidate's footprint, padded by ``gap / 2``, meets any placed car's padded
    footprint: parked pairs at frame 0, pairs with a moving car at every frame."""
    pad = 0.5 * gap
    still = candidate.footprint(0, pad=pad) if not candidate.dynamic else None
    for other in placed:
        if not candidate.dynamic and not other.dynamic:
            if still.intersects(other.footprint(0, pad=pad)):
                return True
            continue
        for i in range(n_frames):
            fp = still if still is not None else candidate.footprint(i, pad=pad)
            if fp.intersects(other.footprint(i, pad=pad)):
                return True
    return False
