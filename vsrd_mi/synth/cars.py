"""Car shapes for the synthetic KITTI-360 generator: CC0 meshes and procedural cars.

Every car model is a triangle mesh in the *car frame* of KITTI-360 boxes: x forward (heading),
y left, z up, metres, with a per-face material (:data:`BODY`, :data:`GLASS`, :data:`TYRE`,
:data:`RIM`) and optionally a :class:`LampLayout` (where the texture paints lamps and plates).
The ground-truth box of a placed car is the tight axis-aligned box of its vertices in this frame
(:attr:`CarModel.box_min` / :attr:`CarModel.box_max`), so a model need not be centred.

Mesh files (the two bundled CC0 meshes, or any given with ``--mesh``) follow the convention of
``vsrd_mi/synth/assets/README.md``: metres, +Y up, length along Z with the front at +Z, origin at
the bottom centre. The meshes are not watertight: they are rendered by ray casting, never voxelised.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from ..errors import DataError

#: Per-face materials of a car model.
BODY, GLASS, TYRE, RIM = 0, 1, 2, 3

#: Folder of the bundled CC0 car meshes.
ASSET_DIR = Path(__file__).resolve().parent / "assets"

#: Mesh-file axes (x = width/left, y = up, z = length/front) -> car frame (x fwd, y left, z up).
MESH_TO_CAR = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class LampLayout:
    """Where the texture paints lamps and number plates on a car (car frame, metres).

    A lamp or plate is painted on body faces that face forwards (front zones) or backwards (rear
    zones) within a band of heights ``z`` and of lateral distances ``|y|`` from the centre plane.
    """

    #: Headlamps: height band and ``|y|`` band; beyond ``indicator_y`` the band is amber.
    head_z: tuple[float, float]
    head_y: tuple[float, float]
    indicator_y: float
    #: Rear lamps (red): height band and ``|y|`` band.
    tail_z: tuple[float, float]
    tail_y: tuple[float, float]
    #: Number plates: height bands at the front and rear, half their width.
    plate_front_z: tuple[float, float]
    plate_rear_z: tuple[float, float]
    plate_half_width: float

    def scaled(self, factor: float) -> "LampLayout":
        """The layout of the car scaled uniformly about its bottom centre by ``factor``."""
        def band(b: tuple[float, float]) -> tuple[float, float]:
            return (b[0] * factor, b[1] * factor)
        return LampLayout(band(self.head_z), band(self.head_y), self.indicator_y * factor,
                          band(self.tail_z), band(self.tail_y), band(self.plate_front_z),
                          band(self.plate_rear_z), self.plate_half_width * factor)


@dataclass(frozen=True)
class CarModel:
    """A car mesh in the car frame (x forward, y left, z up), lowest vertex at z = 0."""

    name: str
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    materials: np.ndarray  # (F,) int8, one of BODY / GLASS / TYRE / RIM
    #: Vehicle class written to the attributes file (procedural class name or mesh file stem).
    vehicle_class: str = ""
    #: Lamps and plates painted by the texture (None: none).
    lamps: LampLayout | None = None

    @property
    def box_min(self) -> np.ndarray:
        return self.vertices.min(axis=0)

    @property
    def box_max(self) -> np.ndarray:
        return self.vertices.max(axis=0)

    @property
    def size(self) -> np.ndarray:
        """Tight box extent ``(length, width, height)`` along the car frame's axes."""
        return self.box_max - self.box_min

    @property
    def box_centre(self) -> np.ndarray:
        """Centre of the tight box in the car frame."""
        return 0.5 * (self.box_min + self.box_max)


#: Cabin outline per body type: ranges of the insets (metres) of the cabin's bottom rear, bottom
#: front, top rear and top front edges from the rear / front ends of the car.
CabinInsets = tuple[tuple[float, float], tuple[float, float], tuple[float, float], tuple[float, float]]

#: Cabin faces whose normal points up more steeply than this are roof (painted), not glass.
ROOF_MIN_NORMAL_Z = 0.9


@dataclass(frozen=True)
class ProceduralCarConfig:
    """Ranges of the procedural car shapes (metres); one row per body type.

    Each type is ``(name, length range, width range, height range)``; the types cover hatchbacks,
    sedans, SUVs and vans up to 5.2 m x 2.3 m x 2.2 m. ``cabins`` holds each type's
    :data:`CabinInsets` in the same order.
    """

    types: tuple[tuple[str, tuple[float, float], tuple[float, float], tuple[float, float]], ...] = (
        ("hatchback", (3.6, 4.3), (1.65, 1.82), (1.40, 1.55)),
        ("sedan", (4.3, 5.0), (1.72, 1.90), (1.36, 1.50)),
        ("suv", (4.3, 5.0), (1.80, 2.05), (1.60, 1.85)),
        ("van", (4.6, 5.2), (1.90, 2.30), (1.90, 2.20)),
    )
    cabins: tuple[CabinInsets, ...] = (
        ((0.05, 0.15), (1.0, 1.25), (0.25, 0.4), (1.8, 2.1)),
        ((0.85, 1.05), (1.2, 1.45), (1.3, 1.5), (2.0, 2.3)),
        ((0.05, 0.15), (1.05, 1.25), (0.15, 0.3), (1.65, 1.9)),
        ((0.02, 0.06), (0.45, 0.7), (0.03, 0.08), (1.0, 1.3)),
    )
    #: The roof is at least this long, metres.
    min_roof_length: float = 0.5
    #: Wheel radius range.
    wheel_radius: tuple[float, float] = (0.29, 0.38)
    #: Tyre width, and the gap between the tyre's outer face and the body side.
    wheel_width: float = 0.21
    wheel_inset: float = 0.01
    #: Distance from a wheel's edge to the car's end (range), metres.
    wheel_overhang: tuple[float, float] = (0.45, 0.75)
    #: Distance between the body bottom and the ground, as a fraction of the wheel radius.
    clearance_fraction: tuple[float, float] = (0.45, 0.7)
    #: Height of the belt line (top of the lower body) as a fraction of the car height.
    belt_fraction: tuple[float, float] = (0.50, 0.60)
    #: Cabin bottom and roof widths as fractions of the body width.
    cabin_width_fraction: float = 0.97
    roof_width_fraction: tuple[float, float] = (0.74, 0.86)
    #: Number of facets around a wheel.
    wheel_sections: int = 14


def _hull(points: np.ndarray) -> trimesh.Trimesh:
    return trimesh.convex.convex_hull(points)


def procedural_car(rng: np.random.Generator, config: ProceduralCarConfig = ProceduralCarConfig(),
                   kind: str | None = None) -> CarModel:
    """A random car: lower body box + cabin (convex hull, windows) + four cylinder wheels.

    ``kind`` picks a body type from ``config.types`` (random when None). The result's tight box is
    exactly (length, width, height) drawn from that type's ranges.
    """
    names = [t[0] for t in config.types]
    idx = int(rng.integers(len(names))) if kind is None else names.index(kind)
    name, l_rng, w_rng, h_rng = config.types[idx]
    length, width, height = (float(rng.uniform(*r)) for r in (l_rng, w_rng, h_rng))
    radius = float(rng.uniform(*config.wheel_radius))
    clearance = radius * float(rng.uniform(*config.clearance_fraction))
    belt = height * float(rng.uniform(*config.belt_fraction))
    roof_w = width * float(rng.uniform(*config.roof_width_fraction))

    parts: list[tuple[trimesh.Trimesh, int]] = []
    body = trimesh.creation.box(bounds=[[-length / 2, -width / 2, clearance],
                                        [length / 2, width / 2, belt]])
    parts.append((body, BODY))

    half = 0.5 * length
    rear_b, front_b, rear_t, front_t = (float(rng.uniform(*r)) for r in config.cabins[idx])
    b0, b1, t0 = -half + rear_b, half - front_b, -half + rear_t
    t1 = max(half - front_t, t0 + config.min_roof_length)
    cw = config.cabin_width_fraction * width
    cabin_pts = np.array([[x, sy * w / 2, z] for (x0, x1, w, z) in ((b0, b1, cw, belt),
                                                                    (t0, t1, roof_w, height))
                          for x in (x0, x1) for sy in (-1, 1)])
    cabin = _hull(cabin_pts)
    parts.append((cabin, GLASS))  # the roof is re-labelled BODY below

    overhang = radius + float(rng.uniform(*config.wheel_overhang))
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            wheel = trimesh.creation.cylinder(radius=radius, height=config.wheel_width,
                                              sections=config.wheel_sections)
            wheel.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
            wheel.apply_translation([sx * (length / 2 - overhang),
                                     sy * (width / 2 - config.wheel_width / 2 - config.wheel_inset),
                                     radius])
            parts.append((wheel, TYRE))

    verts, faces, mats = [], [], []
    offset = 0
    for mesh, mat in parts:
        v = np.asarray(mesh.vertices, dtype=np.float64)
        f = np.asarray(mesh.faces, dtype=np.int64)
        m = np.full(len(f), mat, dtype=np.int8)
        if mesh is cabin:  # roof: faces facing up are painted like the body
            m[np.asarray(mesh.face_normals)[:, 2] > ROOF_MIN_NORMAL_Z] = BODY
        verts.append(v)
        faces.append(f + offset)
        mats.append(m)
        offset += len(v)
    verts = np.concatenate(verts)
    verts[:, 2] -= verts[:, 2].min()  # faceted wheels: put the lowest vertex on the ground
    return CarModel(f"procedural-{name}", verts, np.concatenate(faces), np.concatenate(mats),
                    f"procedural-{name}")


#: Upper part of a mesh-file car (fraction of its height) whose steep faces are painted as glass.
GLASS_HEIGHT_FRACTION = 0.62
#: Faces whose |normal z| is below this are "steep" (windows rather than roof/bonnet).
GLASS_MAX_NORMAL_Z = 0.85


def load_car_mesh(path: str | Path) -> CarModel:
    """Load a car mesh file (see module docstring for its axes) into the car frame.

    Raises :class:`~vsrd_mi.errors.DataError` when the file is missing, unreadable, holds no
    triangles, or has non-finite or degenerate geometry.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "car mesh file does not exist")
    stat = path.stat()
    return _load_car_mesh(str(path.resolve()), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=16)
def _load_car_mesh(name: str, mtime_ns: int, size: int) -> CarModel:
    """Cached body of :func:`load_car_mesh` (keyed by the file's path, time stamp and size)."""
    path = Path(name)
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise DataError(path, f"cannot read car mesh: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise DataError(path, "car mesh holds no triangles")
    verts = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if not np.all(np.isfinite(verts)):
        raise DataError(path, "car mesh has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise DataError(path, "car mesh faces index missing vertices")
    verts = verts @ MESH_TO_CAR.T
    extent = verts.max(axis=0) - verts.min(axis=0)
    if np.any(extent <= 1e-3):
        raise DataError(path, f"car mesh is degenerate (extent {extent.round(4).tolist()} m)")
    verts[:, 2] -= verts[:, 2].min()
    tri = verts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    nz = np.divide(np.abs(normals[:, 2]), norm, out=np.ones_like(norm), where=norm > 0)
    high = tri[:, :, 2].mean(axis=1) > GLASS_HEIGHT_FRACTION * extent[2]
    mats = np.where(high & (nz < GLASS_MAX_NORMAL_Z), GLASS, BODY).astype(np.int8)
    for array in (verts, faces, mats):  # shared by the cache
        array.setflags(write=False)
    return CarModel(path.stem, verts, faces, mats, path.stem)


def bundled_mesh_paths() -> list[Path]:
    """The CC0 car meshes shipped with vsrd-mi."""
    return sorted(ASSET_DIR.glob("*.ply"))


def scaled(model: CarModel, factor: float) -> CarModel:
    """The model uniformly scaled about its bottom centre (z = 0 stays on the ground)."""
    lamps = None if model.lamps is None else model.lamps.scaled(factor)
    return CarModel(model.name, model.vertices * factor, model.faces, model.materials,
                    model.vehicle_class, lamps)


#: Lamp and plate bands of a mesh-file car as fractions of its tight box: heights as fractions of
#: the height, ``|y|`` as fractions of the half width. A mesh file has no lamp geometry of its own;
#: the forward-facing surface of the bundled CC0 meshes lies at 10-60 % of their height and the
#: backward-facing one at 10-70 %, so the bands sit in the upper part of each.
MESH_LAMP_FRACTIONS = {"head_z": (0.40, 0.55), "head_y": (0.55, 0.92), "indicator_y": 0.85,
                       "tail_z": (0.50, 0.66), "tail_y": (0.60, 0.95),
                       "plate_front_z": (0.18, 0.27), "plate_rear_z": (0.32, 0.41)}
#: Half the width of a European number plate (520 mm x 110 mm), metres.
PLATE_HALF_WIDTH = 0.26


def with_mesh_lamps(model: CarModel) -> CarModel:
    """The model with lamps and plates at :data:`MESH_LAMP_FRACTIONS` of its tight box."""
    _, width, height = model.size
    f = MESH_LAMP_FRACTIONS
    def z(band: tuple[float, float]) -> tuple[float, float]:
        return (band[0] * height, band[1] * height)
    def y(band: tuple[float, float]) -> tuple[float, float]:
        return (band[0] * 0.5 * width, band[1] * 0.5 * width)
    lamps = LampLayout(z(f["head_z"]), y(f["head_y"]), f["indicator_y"] * 0.5 * width,
                       z(f["tail_z"]), y(f["tail_y"]), z(f["plate_front_z"]),
                       z(f["plate_rear_z"]), PLATE_HALF_WIDTH)
    return CarModel(model.name, model.vertices, model.faces, model.materials,
                    model.vehicle_class, lamps)
