"""Scenes, rays and integrators of the integrator benchmarks (``vsrd-mi bench integrator`` and its
studies) and of the integrator tests.

Two kinds of random scene: the benchmark's (:func:`random_boxes`: car-sized boxes 5-40 m ahead in
a narrow wedge, so they occlude each other, half of them moving) and the tests' (:func:`random_scene`:
boxes 6-30 m ahead with every third one touching its predecessor, so their SDFs interact). Rays
(:func:`random_rays`, :func:`training_rays`) are aimed at box interiors, at box edges and corners
(grazing) and anywhere in the view. Box dictionaries have the keys of
:func:`vsrd_plugins.box_properties`: ``centre``, ``size``, ``yaw``, ``velocity``, ``dynamic``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins import box_properties
from vsrd_plugins.silhouette import VSRDSilhouetteIntegrator

from ..optimise.losses import to_float

#: Box parameters (traversed names) whose gradients the benchmarks time and compare.
BOX_KEYS = ("centre", "size", "yaw", "velocity")


@dataclass(frozen=True)
class SceneConfig:
    """Random scenes: car-sized boxes in a wedge in front of a camera at the origin (y down)."""

    depth: tuple[float, float] = (5.0, 40.0)  # box centre distance along +z (m)
    half_angle: float = 0.4  # wedge half-angle (rad): boxes crowd and occlude each other
    height: tuple[float, float] = (0.6, 1.2)  # box centre y (m, below the camera)
    width: tuple[float, float] = (1.6, 2.1)
    box_height: tuple[float, float] = (1.4, 1.8)
    length: tuple[float, float] = (3.8, 5.0)
    speed_sigma: float = 0.6  # horizontal velocity std (m per frame) of moving boxes
    max_time: float = 2.0  # ray times uniform in [-max_time, max_time] frames
    placement_tries: int = 20000
    camera_jitter: float = 0.05  # ray origins ~ N(0, jitter) around the origin (m)
    frac_interior: float = 0.6  # rays aimed at box interiors
    frac_edge: float = 0.2  # rays aimed at box edges / corners (grazing); the rest anywhere
    edge_snap: float = 0.67  # per axis, probability that an edge ray's target snaps to a face
    edge_noise: float = 0.01  # relative jitter of snapped targets around the face


@dataclass(frozen=True)
class FDSteps:
    """Central differences of the reference: every box parameter is stepped so that box
    surfaces move by about ``surface_m`` (well below the 1/s = 10 cm over which soft labels vary,
    well above float32 noise; :func:`~vsrd_mi.bench.measure.fd_steps`)."""

    surface_m: float = 0.005
    yaw_lever_m: float = 2.0  # distance from the centre of the box corners a yaw step moves


@dataclass(frozen=True)
class Perturbation:
    """Standard deviations of the random change of the boxes before each timed iteration: about an
    optimisation step's (the sample layout changes as it would in a run)."""

    centre_m: float = 0.03
    size_m: float = 0.001
    yaw_rad: float = 0.001


@dataclass(frozen=True)
class BenchConfig:
    """What ``vsrd-mi bench integrator`` measures (``--quick`` uses :data:`QUICK`)."""

    instances: tuple[int, ...] = (1, 3, 6, 12)
    rays: tuple[int, ...] = (1024, 4096, 16384)
    residual: tuple[bool, ...] = (False, True)
    sharpness: float = 10.0
    temperature: float = 0.1
    warmup_iterations: int = 1
    min_iterations: int = 3
    max_iterations: int = 7
    case_budget_s: float = 15.0  # timed iterations ~ budget / warm-up time, clipped to min..max
    schedule_step: float = 1e-3  # relative sharpness change per iteration
    perturbation: Perturbation = field(default_factory=Perturbation)
    accuracy_rays: int = 512
    ref_spacing: float = 0.05  # reference grid spacing in units of 1/s
    ref_chunk_rays: int = 128
    ref_margin: float = 2.0  # reference grid runs this far (m) beyond the farthest box
    fd: FDSteps = field(default_factory=FDSteps)
    fd_rays: int = 256  # central differences: 2 reference renders per box parameter
    seed: int = 0
    scene: SceneConfig = field(default_factory=SceneConfig)


QUICK = BenchConfig(instances=(1, 6), rays=(1024, 16384))


def random_boxes(rng: np.random.Generator, n: int, cfg: SceneConfig) -> dict[str, np.ndarray]:
    """``n`` non-intersecting (bird's-eye circles) car-sized boxes; every other one moves."""
    sizes = np.stack([rng.uniform(*cfg.width, n), rng.uniform(*cfg.box_height, n),
                      rng.uniform(*cfg.length, n)], 1)
    radius = 0.5 * np.hypot(sizes[:, 0], sizes[:, 2])
    centres = np.zeros((n, 3))
    for i in range(n):
        for _ in range(cfg.placement_tries):
            z = rng.uniform(*cfg.depth)
            c = np.array([z * np.tan(rng.uniform(-cfg.half_angle, cfg.half_angle)),
                          rng.uniform(*cfg.height), z])
            gap = np.hypot(*(centres[:i, [0, 2]] - c[[0, 2]]).T)
            if np.all(gap > radius[:i] + radius[i]):
                centres[i] = c
                break
        else:
            raise RuntimeError(f"bench integrator: cannot place {n} boxes without overlap in the "
                               f"wedge {cfg.depth} m x +-{cfg.half_angle} rad; widen SceneConfig")
    dynamic = (np.arange(n) % 2 == 0).astype(np.float64)
    vel = rng.normal(0.0, cfg.speed_sigma, (n, 3)) * np.array([1.0, 0.0, 1.0]) * dynamic[:, None]
    return {"centre": centres, "size": sizes, "yaw": rng.uniform(-np.pi, np.pi, n),
            "velocity": vel, "dynamic": dynamic}


def random_rays(rng: np.random.Generator, boxes: dict, n: int,
                cfg: SceneConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays ``(o, d, time)`` (NumPy, (n, 3), (n, 3), (n,)); see the module docstring."""
    nb = len(boxes["centre"])
    times = rng.uniform(-cfg.max_time, cfg.max_time, n)
    o = rng.normal(0.0, cfg.camera_jitter, (n, 3))
    k = rng.integers(0, nb, n)
    half = 0.5 * boxes["size"][k]
    local = rng.uniform(-1.0, 1.0, (n, 3)) * half
    kind = rng.uniform(size=n)
    edge = (kind >= cfg.frac_interior) & (kind < cfg.frac_interior + cfg.frac_edge)
    snap = edge[:, None] & (rng.uniform(size=(n, 3)) < cfg.edge_snap)
    local = np.where(snap, np.sign(local) * half * (1.0 + rng.normal(0.0, cfg.edge_noise, (n, 3))), local)
    c, s = np.cos(boxes["yaw"][k]), np.sin(boxes["yaw"][k])
    world = np.stack([c * local[:, 0] + s * local[:, 2], local[:, 1], -s * local[:, 0] + c * local[:, 2]], 1)
    centre = boxes["centre"][k] + boxes["dynamic"][k, None] * boxes["velocity"][k] * times[:, None]
    spread = np.tan(cfg.half_angle)
    anywhere = np.stack([rng.uniform(-spread, spread, n), rng.uniform(-0.15, 0.15, n), np.ones(n)], 1)
    d = np.where((kind >= cfg.frac_interior + cfg.frac_edge)[:, None], anywhere, centre + world - o)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d, times


def random_scene(rng: np.random.Generator, n: int, dynamic: bool = False) -> dict[str, np.ndarray]:
    """The tests' scenes: ``n`` car-like boxes 6-30 m ahead of a camera at the origin, every third
    one beside its predecessor (interacting SDFs); with ``dynamic`` every other one moves."""
    centres = np.stack([rng.uniform(-7, 7, n), rng.uniform(0.3, 1.2, n), rng.uniform(6, 30, n)], 1)
    sizes = np.stack([rng.uniform(1.6, 2.1, n), rng.uniform(1.4, 1.8, n), rng.uniform(3.8, 5.0, n)], 1)
    yaws = rng.uniform(-np.pi, np.pi, n)
    for i in range(1, n, 3):  # every third box sits next to its predecessor
        yaws[i] = yaws[i - 1]
        c, s_ = np.cos(yaws[i]), np.sin(yaws[i])
        side = np.array([c, 0.0, -s_])  # local +x in the scene frame
        gap = rng.uniform(0.05, 0.4)
        centres[i] = centres[i - 1] + side * (0.5 * (sizes[i - 1, 0] + sizes[i, 0]) + gap)
        centres[i, 1] = centres[i - 1, 1]
    vel = rng.normal(0.0, 0.6, (n, 3)) * np.array([1.0, 0.0, 1.0]) if dynamic else np.zeros((n, 3))
    dyn = (np.arange(n) % 2 == 0).astype(float) if dynamic else np.zeros(n)
    return {"centre": centres, "size": sizes, "yaw": yaws, "velocity": vel, "dynamic": dyn}


def training_rays(rng: np.random.Generator, scene: dict, n: int,
                  max_time: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tests' rays from near the origin: 60 % aimed at box interiors, 20 % at box edges and
    corners (grazing), 20 % anywhere in a 90-degree frustum. Returns ``(o, d, time)`` (NumPy)."""
    nb = len(scene["centre"])
    times = rng.uniform(-max_time, max_time, n) if max_time else np.zeros(n)
    o = rng.normal(0.0, 0.05, (n, 3))
    k = rng.integers(0, nb, n)
    half = 0.5 * scene["size"][k]
    local = rng.uniform(-1, 1, (n, 3)) * half
    kind = rng.uniform(size=n)
    edge = (kind >= 0.6) & (kind < 0.8)
    snap = rng.uniform(size=(n, 3)) < 0.67
    local = np.where(edge[:, None] & snap, np.sign(local) * half * (1.0 + rng.normal(0, 0.01, (n, 3))), local)
    yaw = scene["yaw"][k]
    c, s_ = np.cos(yaw), np.sin(yaw)
    world = np.stack([c * local[:, 0] + s_ * local[:, 2], local[:, 1], -s_ * local[:, 0] + c * local[:, 2]], 1)
    centre = scene["centre"][k] + scene["dynamic"][k, None] * scene["velocity"][k] * times[:, None]
    target = centre + world
    anywhere = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.3, 0.3, n), np.ones(n)], 1)
    d = np.where((kind >= 0.8)[:, None], anywhere, target - o)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d, times


def to_rays(o: np.ndarray, d: np.ndarray, t: np.ndarray) -> tuple[mi.Point3f, mi.Vector3f, mi.Float]:
    """NumPy rays ``(o, d, time)`` as Dr.Jit arrays (Dr.Jit-owned memory)."""
    return (mi.Point3f(*[to_float(o[:, j]) for j in range(3)]), mi.Vector3f(*[to_float(d[:, j]) for j in range(3)]),
            to_float(t))


@dataclass
class RayBatch:
    """Rays and per-instance loss weights as Dr.Jit arrays (Dr.Jit-owned memory)."""

    o: mi.Point3f
    d: mi.Vector3f
    time: mi.Float
    weights: list[mi.Float]

    @staticmethod
    def from_numpy(o: np.ndarray, d: np.ndarray, t: np.ndarray, w: np.ndarray) -> "RayBatch":
        return RayBatch(mi.Point3f(*[to_float(o[:, j]) for j in range(3)]),
                        mi.Vector3f(*[to_float(d[:, j]) for j in range(3)]), to_float(t),
                        [to_float(row) for row in w])

    @property
    def width(self) -> int:
        return dr.width(self.time)


@dataclass
class CaseData:
    """One scene with its ray set (the largest ray count; smaller counts use prefixes)."""

    boxes: dict[str, np.ndarray]
    o: np.ndarray
    d: np.ndarray
    t: np.ndarray
    w: np.ndarray  # (instances, rays) loss weights

    @staticmethod
    def generate(seed: int, n_inst: int, n_rays: int, cfg: SceneConfig) -> "CaseData":
        rng = np.random.default_rng(seed)
        boxes = random_boxes(rng, n_inst, cfg)
        o, d, t = random_rays(rng, boxes, n_rays, cfg)
        return CaseData(boxes, o, d, t, rng.normal(size=(n_inst, n_rays)))

    def batch(self, n: int) -> RayBatch:
        return RayBatch.from_numpy(self.o[:n], self.d[:n], self.t[:n], self.w[:, :n])


def case_seed(cfg: BenchConfig, n_inst: int, residual: bool) -> int:
    return cfg.seed + 1000 * n_inst + (1 if residual else 0)


def case_data(cfg: BenchConfig, n_inst: int, residual: bool) -> tuple[CaseData, CaseData]:
    """The scene and rays of an (instances, residual) pair, and a fresh pair for warm first calls."""
    seed = case_seed(cfg, n_inst, residual)
    return (CaseData.generate(seed, n_inst, max(cfg.rays), cfg.scene),
            CaseData.generate(seed + 500, n_inst, max(cfg.rays), cfg.scene))


def integrator_description(boxes: dict, sampling: str, residual: bool, sharpness: float, temperature: float,
                           **properties) -> dict:
    """``mi.load_dict`` description of a ``vsrd_silhouette`` integrator holding ``boxes``, with
    further plugin ``properties``."""
    return {"type": "vsrd_silhouette", "sampling": sampling, "residual": residual, "sharpness": sharpness,
            "temperature": temperature, **box_properties(**boxes), **properties}


def load_integrator(boxes: dict, sampling: str, residual: bool, cfg: BenchConfig,
                    **settings) -> VSRDSilhouetteIntegrator:
    """The benchmark's integrator (:func:`integrator_description` at the configured schedule),
    with internal ``settings`` changed (e.g. ``residual_tail=0``,
    :class:`~vsrd_plugins.silhouette.settings.SilhouetteSettings`)."""
    it = mi.load_dict(integrator_description(boxes, sampling, residual, cfg.sharpness, cfg.temperature))
    if settings:
        it.settings = replace(it.settings, **settings)
    return it



#: ``vsrd_silhouette`` plugin properties other than the boxes (:func:`silhouette_integrator`).
SILHOUETTE_PROPERTIES = ("sampling", "band_samples", "near", "far", "sharpness", "temperature", "residual",
                         "residual_seed")


def silhouette_integrator(scene: dict, **options) -> VSRDSilhouetteIntegrator:
    """A ``vsrd_silhouette`` integrator holding the boxes of ``scene`` (keys of
    :func:`vsrd_plugins.box_properties`); ``options`` are plugin properties
    (:data:`SILHOUETTE_PROPERTIES`) or internal settings
    (:class:`~vsrd_plugins.silhouette.settings.SilhouetteSettings` fields)."""
    properties = {k: v for k, v in options.items() if k in SILHOUETTE_PROPERTIES}
    settings = {k: v for k, v in options.items() if k not in SILHOUETTE_PROPERTIES}
    it = mi.load_dict({"type": "vsrd_silhouette", **box_properties(**scene), **properties})
    if settings:
        it.settings = replace(it.settings, **settings)
    return it
