"""``vsrd-mi bench integrator``: dense vs adaptive sampling of ``vsrd_silhouette``, side by side.

For every case (instances x rays x residual on/off) one random scene of car-sized boxes 5-40 m in
front of a camera at the origin (a narrow wedge, so boxes occlude each other; half of them move
with the ray time) and one ray batch (60 % aimed at box interiors, 20 % at box edges and corners,
i.e. grazing, 20 % anywhere in the view) are rendered with ``render_rays`` by a ``dense`` and an
``adaptive`` integrator loaded with ``mi.load_dict`` from the same integrator dictionary. Measured:

* **time per iteration**: forward + backward of a random-weighted sum of the soft labels, up to the
  evaluated gradients of all box parameters; the median of several warm iterations. Dense and
  adaptive iterations alternate, so load from other processes on a shared machine hits both.
  Before each iteration the box parameters move by an optimiser-step-sized random amount and the
  sharpness changes slightly, as in an optimisation loop.
* **cold first iteration**: the first call for the case in this process (kernels are compiled,
  or loaded from the on-disk kernel cache: ``cold_*`` counts both; see ``--fresh-cache``) and
  **warm first iteration**: the first call of a freshly loaded integrator on a new scene and new
  rays of the same case, after the case has run (kernels in memory).
* **kernel compilations per iteration after warm-up**: JIT kernel-history entries missing from
  the in-memory kernel cache in each timed iteration (must be 0): ``cache_hit`` false (compiled)
  or ``cache_disk`` true (loaded from the disk cache, which Dr.Jit reports with ``cache_hit``
  true, so ``cache_hit`` alone misses recompilations of kernels an earlier process wrote).
* **accuracy** on the first ``accuracy_rays`` rays of an instance count's ray set (shared by its
  ray counts, which use nested prefixes of one set), rendered by the samplers within the whole
  set, as the largest timed case renders them: soft-label error (per ray the largest
  |difference| over instances; max and 99th percentile over rays) and the cosine of the gradients
  w.r.t. all box parameters, adaptive vs dense and each vs a brute-force reference: the
  integrator's own integral (``integrate_at``) on a uniform grid of spacing
  ``ref_spacing / s`` (the dense 100 + 100 sampler itself is up to ~0.4 off on grazing rays).
  The AD gradient of a sampled integral, the reference's included, is one-sided where a ray's
  deepest sample inside a box lies on a ridge of the box SDF (see
  :func:`reference_fd_gradient`), so all three AD gradients are also compared with central
  differences of the reference labels on the first ``fd_rays`` rays (``grad_cosine_vs_reference_fd``).

Outputs: JSON (``--json PATH``; per case ``speedup``, ``max_abs_diff``, ``grad_cosine``, timings,
compilation counts), a CSV and a PNG plot next to it (same stem).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins.sdf import instance_properties
from vsrd_plugins.silhouette import VSRDSilhouetteIntegrator

from ..optimise.losses import to_float, to_uint

#: Box parameters whose gradients are timed and compared.
BOX_KEYS = ("box_dims", "box_centre", "box_yaw", "box_velocity")
SAMPLINGS = ("dense", "adaptive")
#: Environment variable marking the child process started by ``--fresh-cache``.
FRESH_CACHE_CHILD = "VSRD_MI_BENCH_FRESH_CACHE_CHILD"
#: Dr.Jit's kernel cache directory variable (default ``~/.drjit``).
DRJIT_CACHE_ENV = "DRJIT_CACHE_DIR"
#: The speed target of the task: adaptive at least this much faster than dense at 6 / 16k.
TARGET_SPEEDUP = 10.0
TARGET_CASE = (6, 16384)


# ----------------------------------------------------------------------------------------------
# configuration
# ----------------------------------------------------------------------------------------------


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
    """Central differences of the reference: every raw box parameter is stepped so that box
    surfaces move by about ``surface_m`` (well below the 1/s = 10 cm over which soft labels vary,
    well above float32 noise), through the decoding's Jacobian (:func:`fd_steps`)."""

    surface_m: float = 0.005
    yaw_lever_m: float = 2.0  # distance from the centre of the box corners a yaw step moves


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
    perturbation: float = 1e-3  # std of the raw box parameter change per iteration (~3 cm centre)
    accuracy_rays: int = 512
    ref_spacing: float = 0.05  # reference grid spacing in units of 1/s
    ref_chunk_rays: int = 128
    ref_margin: float = 2.0  # reference grid runs this far (m) beyond the farthest box
    fd: FDSteps = field(default_factory=FDSteps)
    fd_rays: int = 256  # central differences: 2 reference renders per box parameter
    seed: int = 0
    scene: SceneConfig = field(default_factory=SceneConfig)


QUICK = BenchConfig(instances=(1, 6), rays=(1024, 16384))


# ----------------------------------------------------------------------------------------------
# scenes and rays
# ----------------------------------------------------------------------------------------------


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
    return {"centres": centres, "sizes": sizes, "yaws": rng.uniform(-np.pi, np.pi, n),
            "velocities": vel, "dynamic": dynamic}


def random_rays(rng: np.random.Generator, boxes: dict, n: int,
                cfg: SceneConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays ``(o, d, time)`` (NumPy, (n, 3), (n, 3), (n,)); see the module docstring."""
    nb = len(boxes["centres"])
    times = rng.uniform(-cfg.max_time, cfg.max_time, n)
    o = rng.normal(0.0, cfg.camera_jitter, (n, 3))
    k = rng.integers(0, nb, n)
    half = 0.5 * boxes["sizes"][k]
    local = rng.uniform(-1.0, 1.0, (n, 3)) * half
    kind = rng.uniform(size=n)
    edge = (kind >= cfg.frac_interior) & (kind < cfg.frac_interior + cfg.frac_edge)
    snap = edge[:, None] & (rng.uniform(size=(n, 3)) < cfg.edge_snap)
    local = np.where(snap, np.sign(local) * half * (1.0 + rng.normal(0.0, cfg.edge_noise, (n, 3))), local)
    c, s = np.cos(boxes["yaws"][k]), np.sin(boxes["yaws"][k])
    world = np.stack([c * local[:, 0] + s * local[:, 2], local[:, 1], -s * local[:, 0] + c * local[:, 2]], 1)
    centre = boxes["centres"][k] + boxes["dynamic"][k, None] * boxes["velocities"][k] * times[:, None]
    spread = np.tan(cfg.half_angle)
    anywhere = np.stack([rng.uniform(-spread, spread, n), rng.uniform(-0.15, 0.15, n), np.ones(n)], 1)
    d = np.where((kind >= cfg.frac_interior + cfg.frac_edge)[:, None], anywhere, centre + world - o)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d, times


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


def integrator_description(boxes: dict, sampling: str, residual: bool, cfg: BenchConfig) -> dict:
    return {"type": "vsrd_silhouette", "sampling": sampling, "residual": residual,
            "sharpness": cfg.sharpness, "temperature": cfg.temperature, **instance_properties(**boxes)}


def load_integrator(boxes: dict, sampling: str, residual: bool, cfg: BenchConfig, **options) -> VSRDSilhouetteIntegrator:
    """The benchmark's integrator (:func:`integrator_description`), with integrator ``options``
    on top (e.g. ``residual_tail=0``)."""
    return mi.load_dict({**integrator_description(boxes, sampling, residual, cfg), **options})


# ----------------------------------------------------------------------------------------------
# measurement primitives
# ----------------------------------------------------------------------------------------------


@dataclass
class KernelCounts:
    """JIT kernels of a stretch of code (from Dr.Jit's kernel history).

    A kernel missing from the in-memory cache was either compiled (``cache_hit`` false) or loaded
    from the on-disk cache (Dr.Jit reports those with ``cache_hit`` *and* ``cache_disk`` true, so
    counting ``cache_hit`` false alone misses every recompilation of a kernel some earlier process
    already wrote to disk); :attr:`misses` counts both.
    """

    launched: int = 0
    compiled: int = 0
    from_disk: int = 0
    compile_ms: float = 0.0  # LLVM time of the kernels compiled from scratch

    @property
    def misses(self) -> int:
        return self.compiled + self.from_disk


class kernel_history:
    """Context manager recording :class:`KernelCounts` (``KernelHistory`` flag on inside)."""

    def __enter__(self) -> KernelCounts:
        self._old = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()  # clear
        self.counts = KernelCounts()
        return self.counts

    def __exit__(self, *exc) -> None:
        for k in dr.kernel_history():
            if k.get("type") != dr.KernelType.JIT:
                continue
            self.counts.launched += 1
            if k.get("cache_disk", False):
                self.counts.from_disk += 1
            elif not k.get("cache_hit", False):
                self.counts.compiled += 1
                self.counts.compile_ms += float(k.get("backend_time", 0.0))
        dr.set_flag(dr.JitFlag.KernelHistory, self._old)


def new_kernels(seen: set) -> int:
    """JIT kernels in Dr.Jit's kernel history (since it was last read) whose code, by hash, is
    not in ``seen``; ``seen`` takes them. Unlike a count of cache misses, a kernel that an
    earlier process wrote to the disk cache still counts as new where this process generates
    it anew (a value baked into its code). Needs ``JitFlag.KernelHistory``."""
    hashes = {k["hash"] for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT}
    fresh = len(hashes - seen)
    seen |= hashes
    return fresh


def weighted_loss(labels: list[mi.Float], weights: list[mi.Float]) -> mi.Float:
    """``sum_k sum_rays w_k * label_k`` over the instance labels."""
    total = dr.sum(labels[0] * weights[0])
    for lab, w in zip(labels[1:], weights[1:]):
        total = total + dr.sum(lab * w)
    return total


def labels_and_gradient(it: VSRDSilhouetteIntegrator, chunks: Iterator[tuple[Callable, list[mi.Float]]]
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Instance labels (instances, rays) and the gradient of :func:`weighted_loss` w.r.t. all box
    parameters, accumulated over ``(render, weights)`` chunks of rays."""
    for k in BOX_KEYS:
        dr.enable_grad(it.field.params[k])
    values = []
    for render, weights in chunks:
        labels = render()[:it.field.n]
        dr.backward(weighted_loss(labels, weights))
        values.append(np.stack([np.array(dr.detach(x)) for x in labels]))
    grad = np.concatenate([np.array(dr.grad(it.field.params[k])) for k in BOX_KEYS])
    for k in BOX_KEYS:
        it.field.params[k] = dr.detach(it.field.params[k])
    return np.concatenate(values, axis=1), grad


class TimedIntegrator:
    """An integrator on a ray batch, run as an optimisation step would run it."""

    def __init__(self, it: VSRDSilhouetteIntegrator, batch: RayBatch, cfg: BenchConfig, seed: int):
        self.it, self.batch, self.cfg = it, batch, cfg
        self.base = {k: np.array(it.field.params[k], dtype=np.float64) for k in BOX_KEYS}
        self.rng = np.random.default_rng(seed)
        self.calls = 0

    def step(self) -> tuple[float, KernelCounts]:
        """Move the boxes and the sharpness a little, then time forward + backward."""
        it, cfg = self.it, self.cfg
        if self.calls:
            for k in ("box_dims", "box_centre", "box_yaw"):
                it.field.params[k] = to_float(self.base[k] + self.rng.normal(0.0, cfg.perturbation,
                                                                             self.base[k].shape))
        s = cfg.sharpness * (1.0 + cfg.schedule_step * self.calls)
        it.set_schedule(s, cfg.temperature)
        params = [it.field.params[k] for k in BOX_KEYS]
        dr.eval(params)
        dr.sync_thread()
        with kernel_history() as counts:
            start = time.perf_counter()
            for p in params:
                dr.enable_grad(p)
            labels = it.render_rays(self.batch.o, self.batch.d, self.batch.time)
            dr.backward(weighted_loss(labels[:it.field.n], self.batch.weights))
            grads = [dr.grad(p) for p in params]
            dr.eval(grads)
            dr.sync_thread()
            seconds = time.perf_counter() - start
        for k, p in zip(BOX_KEYS, params):
            it.field.params[k] = dr.detach(p)
        self.calls += 1
        return seconds, counts

    def restore(self) -> None:
        for k in BOX_KEYS:
            self.it.field.params[k] = to_float(self.base[k])
        self.it.set_schedule(self.cfg.sharpness, self.cfg.temperature)


def reference_samples(boxes: dict, cfg: BenchConfig) -> tuple[float, int]:
    """Extent (m) and sample count of the reference grid: spacing ``ref_spacing / s`` from 0 to
    ``ref_margin`` beyond the farthest point any (moving) box reaches."""
    far = float((np.linalg.norm(boxes["centres"], axis=1) + 0.5 * np.linalg.norm(boxes["sizes"], axis=1)
                 + np.linalg.norm(boxes["velocities"], axis=1) * cfg.scene.max_time).max() + cfg.ref_margin)
    return far, int(np.ceil(far * cfg.sharpness / cfg.ref_spacing))


#: Ternary-search iterations of :func:`deepest_points` (float64; shrinks the bracket by 1.5^-n).
DEEPEST_ITERATIONS = 100


def deepest_points(boxes: dict[str, np.ndarray], o: np.ndarray, d: np.ndarray, time: np.ndarray,
                   t_max: float) -> np.ndarray:
    """``(rays, boxes)`` ray parameters in ``[0, t_max]`` of each box's least SDF along each ray
    (closest approach, or deepest point inside), by float64 ternary search: the exact box SDF is
    convex along a line. Boxes as :meth:`InstanceField.numpy_boxes` (dynamic ones at the ray time)."""
    c, s = np.cos(boxes["yaws"]), np.sin(boxes["yaws"])
    centre = boxes["centres"][None] + (boxes["dynamic"][:, None] * boxes["velocities"])[None] * time[:, None, None]
    half = 0.5 * boxes["sizes"][None]

    def sdf(t: np.ndarray) -> np.ndarray:
        q = o[:, None] + t[..., None] * d[:, None] - centre  # (rays, boxes, 3) scene frame
        local = np.stack([c * q[..., 0] - s * q[..., 2], q[..., 1], s * q[..., 0] + c * q[..., 2]], -1)
        e = np.abs(local) - half
        return np.linalg.norm(np.maximum(e, 0.0), axis=-1) + np.minimum(e.max(-1), 0.0)

    lo = np.zeros((len(o), len(c)))
    hi = np.full_like(lo, t_max)
    for _ in range(DEEPEST_ITERATIONS):
        m1, m2 = lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0
        left = sdf(m1) < sdf(m2)
        lo, hi = np.where(left, lo, m1), np.where(left, m2, hi)
    return 0.5 * (lo + hi)


def reference_grid(boxes: dict[str, np.ndarray], o: np.ndarray, d: np.ndarray, time: np.ndarray,
                   far: float | np.ndarray, m: int, near: float | np.ndarray = 0.0) -> tuple[mi.Float, int]:
    """Sorted samples of the reference integral per ray: the uniform grid of ``m`` samples on
    ``[near, far]`` (numbers, or one per ray) plus every box's deepest point along the ray
    (:func:`deepest_points`, clipped to that stretch). The grid alone puts a ray's deepest
    sample up to a spacing away from the true minimum, so its labels (and their finite
    differences, which then follow a fixed sample's one-sided face) would lag the converged
    integral by up to ``s * spacing`` in ``Phi_s``'s argument."""
    grid = np.broadcast_to(np.linspace(near, far, m, axis=-1), (len(o), m))
    deep = deepest_points(boxes, o, d, time, float(np.max(far)))
    deep = np.clip(deep, np.reshape(near, (-1, 1)), np.reshape(far, (-1, 1)))
    t = np.sort(np.concatenate([grid, deep], axis=1), axis=1)
    return mi.Float(np.ascontiguousarray(t.ravel(), dtype=np.float32)), t.shape[1]


def reference_chunk(it: VSRDSilhouetteIntegrator, data: CaseData, start: int, stop: int,
                    cfg: BenchConfig) -> tuple[Callable[[], list[mi.Float]], list[mi.Float]]:
    """Renderer and loss weights of rays ``start:stop`` for the brute-force reference: the
    integrator's NeuS integral (``integrate_at``) on :func:`reference_grid` (the deepest points
    follow the integrator's current boxes, so finite differences see them move)."""
    far, m = reference_samples(data.boxes, cfg)
    n = stop - start
    sub = RayBatch.from_numpy(data.o[start:stop], data.d[start:stop], data.t[start:stop], data.w[:, start:stop])
    o, d, tm = data.o[start:stop], data.d[start:stop], data.t[start:stop]
    rays = to_uint(np.arange(n))

    def render() -> list[mi.Float]:
        t, mm = reference_grid(it.field.numpy_boxes(), o, d, tm, far, m)
        return it.integrate_at(it.field.decode(), rays, sub.o, sub.d, sub.time, t, mm)

    return render, sub.weights



def reference_chunks(it: VSRDSilhouetteIntegrator, data: CaseData, n: int, cfg: BenchConfig
                     ) -> Iterator[tuple[Callable[[], list[mi.Float]], list[mi.Float]]]:
    """:func:`reference_chunk` over the first ``n`` rays, ``ref_chunk_rays`` at a time."""
    for a in range(0, n, cfg.ref_chunk_rays):
        yield reference_chunk(it, data, a, min(a + cfg.ref_chunk_rays, n), cfg)


# ----------------------------------------------------------------------------------------------
# accuracy
# ----------------------------------------------------------------------------------------------


def label_error(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Per ray the largest |a - b| over instances; its max, 99th percentile and mean over rays."""
    err = np.abs(a - b).max(axis=0)
    return {"max_abs": float(err.max()), "p99_abs": float(np.quantile(err, 0.99)),
            "mean_abs": float(err.mean())}


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else float("nan")


def fd_steps(it: VSRDSilhouetteIntegrator, cfg: BenchConfig) -> dict[str, np.ndarray]:
    """Per raw box parameter, the step moving box surfaces by ~``cfg.fd.surface_m``.

    Centres and half-sizes decode as ``lo + (hi - lo) sigmoid(raw)``, so a raw step ``e`` moves
    them by ``(hi - lo) sigmoid'(raw) e``; the yaw pair ``v = (cos, sin)`` turns by up to
    ``e / |v|`` rad; a velocity step ``e`` moves a box by up to ``max_time * e``.
    """
    r, step = it.field.ranges, cfg.fd.surface_m
    raw = {k: np.array(it.field.params[k], dtype=np.float64) for k in BOX_KEYS}

    def sigmoid_step(x: np.ndarray, lo, hi) -> np.ndarray:
        span = np.tile(np.array(hi) - np.array(lo), len(x) // 3)
        sig = 1.0 / (1.0 + np.exp(-x))
        return step / (span * sig * (1.0 - sig))

    yaw_norm = np.repeat(np.hypot(raw["box_yaw"][0::2], raw["box_yaw"][1::2]), 2)
    return {"box_dims": sigmoid_step(raw["box_dims"], r.half_lo, r.half_hi),
            "box_centre": sigmoid_step(raw["box_centre"], r.centre_lo, r.centre_hi),
            "box_yaw": step / cfg.fd.yaw_lever_m * yaw_norm,
            "box_velocity": np.full(len(raw["box_velocity"]), step / cfg.scene.max_time)}


def reference_fd_gradient(data: CaseData, residual: bool, n: int, cfg: BenchConfig) -> np.ndarray:
    """Central differences of :func:`weighted_loss` of the reference labels of the first ``n`` rays
    w.r.t. every raw box parameter (steps :func:`fd_steps`), in the order of :data:`BOX_KEYS`.

    The derivative of the converged soft labels. The AD gradient of any sampled integral
    (the reference's included) is one-sided where the deepest sample of a ray inside a box sits
    on a ridge of the box SDF (the max over face planes): it follows one face, while the
    continuous integral's derivative blends the faces meeting there.
    """
    it = load_integrator(data.boxes, "dense", residual, cfg)
    chunks = list(reference_chunks(it, data, n, cfg))
    weights = [np.stack([np.array(w, dtype=np.float64) for w in ws]) for _, ws in chunks]

    def loss() -> float:
        with dr.suspend_grad():
            total = 0.0
            for (render, _), w in zip(chunks, weights):
                labels = render()[:it.field.n]
                total += float((np.stack([np.array(x, dtype=np.float64) for x in labels]) * w).sum())
            return total

    return central_differences(it, loss, fd_steps(it, cfg))


def central_differences(it: VSRDSilhouetteIntegrator, loss: Callable[[], float],
                        steps: dict[str, np.ndarray]) -> np.ndarray:
    """Central differences of ``loss()`` w.r.t. every raw box parameter of ``it`` (in the order
    of :data:`BOX_KEYS`), each stepped by ``steps[key][i]``; the parameters are restored."""
    grad = []
    for key in BOX_KEYS:
        base = np.array(it.field.params[key], dtype=np.float64)
        for i, eps in enumerate(steps[key]):
            values = []
            for sign in (1.0, -1.0):
                x = base.copy()
                x[i] += sign * eps
                it.field.params[key] = to_float(x)
                values.append(loss())
            grad.append((values[0] - values[1]) / (2.0 * float(eps)))
        it.field.params[key] = to_float(base)
    return np.array(grad)


def labels_and_gradients(data: CaseData, residual: bool, n: int, cfg: BenchConfig
                         ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, float]]:
    """Labels and AD gradients of adaptive, dense and the reference on the first ``n`` rays, and
    the seconds each took. The samplers render the case's whole ray set, as the timed steps
    do at its largest ray count (the adaptive sampler lays out a large batch differently:
    isolated rays with the residual field get their own sample groups only where enough of
    them pay for those), with the loss weights of the rays past the first ``n`` set to 0."""
    batch = data.batch(len(data.t))
    first = to_float((np.arange(len(data.t)) < n).astype(np.float32))
    weights = [w * first for w in batch.weights]
    out, seconds = {}, {}
    for name in SAMPLINGS + ("reference",):
        it = load_integrator(data.boxes, "dense" if name == "reference" else name, residual, cfg)
        start = time.perf_counter()
        if name == "reference":
            out[name] = labels_and_gradient(it, reference_chunks(it, data, n, cfg))
        else:
            labels, grad = labels_and_gradient(it, iter([(lambda it=it: it.render_rays(batch.o, batch.d, batch.time),
                                                          weights)]))
            out[name] = (labels[:, :n], grad)
        seconds[name] = time.perf_counter() - start
    return out, seconds


def accuracy(data: CaseData, residual: bool, cfg: BenchConfig) -> dict:
    """Label errors and gradient cosines of adaptive, dense and the reference on the first
    ``accuracy_rays`` rays, and the AD gradients' cosines with central differences of the
    reference on the first ``fd_rays`` rays."""
    n = min(cfg.accuracy_rays, len(data.t))
    out, seconds = labels_and_gradients(data, residual, n, cfg)
    pairs = {"adaptive_vs_dense": ("adaptive", "dense"), "adaptive_vs_reference": ("adaptive", "reference"),
             "dense_vs_reference": ("dense", "reference")}
    result = {"rays": n, "seconds": seconds}
    for key, (a, b) in pairs.items():
        result[key] = {**label_error(out[a][0], out[b][0]), "grad_cosine": cosine(out[a][1], out[b][1])}
    n_fd = min(cfg.fd_rays, n)
    if n_fd < n:
        out, _ = labels_and_gradients(data, residual, n_fd, cfg)
    start = time.perf_counter()
    fd = reference_fd_gradient(data, residual, n_fd, cfg)
    seconds["reference_fd"] = time.perf_counter() - start
    result["fd_rays"] = n_fd
    result["grad_cosine_vs_reference_fd"] = {name: cosine(out[name][1], fd) for name in out}
    result["reference_samples_per_ray"] = reference_samples(data.boxes, cfg)[1]
    return result


# ----------------------------------------------------------------------------------------------
# one case, the whole grid
# ----------------------------------------------------------------------------------------------


def counts_dict(c: KernelCounts) -> dict:
    return {**dataclasses.asdict(c), "misses": c.misses}


def time_case(data: CaseData, fresh: CaseData, n_rays: int, residual: bool, cfg: BenchConfig,
              log: Callable[[str], None]) -> dict:
    """Cold, warm-up and timed iterations of dense and adaptive (alternating), then a warm first
    iteration of each on a fresh scene."""
    runs = {s: TimedIntegrator(load_integrator(data.boxes, s, residual, cfg), data.batch(n_rays), cfg,
                               cfg.seed + 7) for s in SAMPLINGS}
    res = {s: {} for s in SAMPLINGS}
    for s, run in runs.items():
        sec, counts = run.step()
        res[s].update(cold_first_iter_s=sec, cold_kernels=counts_dict(counts))
        log(f"    {s:8s} cold {sec:7.2f} s ({counts.misses} kernel misses, {counts.from_disk} from disk)")
    warm = {s: [] for s in SAMPLINGS}
    for _ in range(cfg.warmup_iterations):
        for s, run in runs.items():
            warm[s].append(run.step()[0])
    iters = {s: int(np.clip(round(cfg.case_budget_s / max(min(warm[s]), 1e-6)), cfg.min_iterations,
                            cfg.max_iterations)) for s in SAMPLINGS}
    times = {s: [] for s in SAMPLINGS}
    misses = {s: [] for s in SAMPLINGS}
    compile_ms = {s: [] for s in SAMPLINGS}
    for i in range(max(iters.values())):
        for s, run in runs.items():
            if i < iters[s]:
                sec, counts = run.step()
                times[s].append(sec)
                misses[s].append(counts.misses)
                compile_ms[s].append(counts.compile_ms)
    for s, run in runs.items():
        res[s].update(iter_s_median=statistics.median(times[s]), iter_s=times[s], warmup_s=warm[s],
                      compiles_per_iter_after_warmup=misses[s], compile_ms_per_iter_after_warmup=compile_ms[s],
                      stats=dict(run.it.last_stats))
        run.restore()
    for s in SAMPLINGS:  # a freshly loaded integrator, new boxes and rays: kernels in memory
        run = TimedIntegrator(load_integrator(fresh.boxes, s, residual, cfg), fresh.batch(n_rays), cfg,
                              cfg.seed + 8)
        sec, counts = run.step()
        res[s].update(warm_first_iter_s=sec, warm_first_kernels=counts_dict(counts))
    for s in SAMPLINGS:
        log(f"    {s:8s} median {res[s]['iter_s_median']:7.3f} s over {len(times[s])} "
            f"(warm first {res[s]['warm_first_iter_s']:.3f} s, compiles/iter {misses[s]})")
    return res


def case_seed(cfg: BenchConfig, n_inst: int, residual: bool) -> int:
    return cfg.seed + 1000 * n_inst + (1 if residual else 0)


def case_data(cfg: BenchConfig, n_inst: int, residual: bool) -> tuple[CaseData, CaseData]:
    """The scene and rays of an (instances, residual) pair, and a fresh pair for warm first calls."""
    seed = case_seed(cfg, n_inst, residual)
    return (CaseData.generate(seed, n_inst, max(cfg.rays), cfg.scene),
            CaseData.generate(seed + 500, n_inst, max(cfg.rays), cfg.scene))


def run_benchmark(cfg: BenchConfig, log: Callable[[str], None] = print) -> list[dict]:
    """Every case of the grid; accuracy once per (instances, residual) (nested ray prefixes)."""
    cases = []
    for residual in cfg.residual:
        for n_inst in cfg.instances:
            seed = case_seed(cfg, n_inst, residual)
            data, fresh = case_data(cfg, n_inst, residual)
            rows = []
            for n_rays in cfg.rays:
                log(f"  instances {n_inst:2d}, rays {n_rays:5d}, residual {residual}")
                res = time_case(data, fresh, n_rays, residual, cfg, log)
                dense, adaptive = res["dense"]["iter_s_median"], res["adaptive"]["iter_s_median"]
                rows.append({"instances": n_inst, "rays": n_rays, "residual": residual, "seed": seed,
                             "speedup": dense / adaptive, **res})
            log(f"  accuracy: instances {n_inst}, residual {residual}")
            acc = accuracy(data, residual, cfg)
            log("    " + ", ".join(f"{k}: max {acc[k]['max_abs']:.4f} p99 {acc[k]['p99_abs']:.4f} "
                                   f"cos {acc[k]['grad_cosine']:.4f}"
                                   for k in ("adaptive_vs_dense", "adaptive_vs_reference", "dense_vs_reference")))
            log("    gradient cosine vs central differences of the reference: " + ", ".join(
                f"{k} {v:.4f}" for k, v in acc["grad_cosine_vs_reference_fd"].items()))
            for row in rows:
                row.update(max_abs_diff=acc["adaptive_vs_dense"]["max_abs"],
                           p99_abs_diff=acc["adaptive_vs_dense"]["p99_abs"],
                           grad_cosine=acc["adaptive_vs_dense"]["grad_cosine"], accuracy=acc)
            cases.extend(rows)
    return cases


# ----------------------------------------------------------------------------------------------
# outputs
# ----------------------------------------------------------------------------------------------


CSV_COLUMNS = ("instances", "rays", "residual", "dense_iter_s", "adaptive_iter_s", "speedup",
               "dense_cold_s", "adaptive_cold_s", "dense_warm_first_s", "adaptive_warm_first_s",
               "dense_compiles_after_warmup", "adaptive_compiles_after_warmup",
               "max_abs_diff", "p99_abs_diff", "grad_cosine",
               "adaptive_ref_max_abs", "adaptive_ref_p99_abs", "adaptive_ref_grad_cosine",
               "dense_ref_max_abs", "dense_ref_p99_abs", "dense_ref_grad_cosine",
               "adaptive_fd_grad_cosine", "dense_fd_grad_cosine", "reference_fd_grad_cosine")


def csv_row(case: dict) -> dict:
    acc = case["accuracy"]
    row = {k: case[k] for k in ("instances", "rays", "residual", "speedup", "max_abs_diff",
                                "p99_abs_diff", "grad_cosine")}
    for s in SAMPLINGS:
        r = case[s]
        row.update({f"{s}_iter_s": r["iter_s_median"], f"{s}_cold_s": r["cold_first_iter_s"],
                    f"{s}_warm_first_s": r["warm_first_iter_s"],
                    f"{s}_compiles_after_warmup": max(r["compiles_per_iter_after_warmup"])})
        ref = acc[f"{s}_vs_reference"]
        row.update({f"{s}_ref_max_abs": ref["max_abs"], f"{s}_ref_p99_abs": ref["p99_abs"],
                    f"{s}_ref_grad_cosine": ref["grad_cosine"]})
    for name, value in acc["grad_cosine_vs_reference_fd"].items():
        row[f"{name}_fd_grad_cosine"] = value
    return row


def write_csv(path: Path, cases: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for case in cases:
            row = csv_row(case)
            writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})


def write_plot(path: Path, cases: list[dict], title: str) -> None:
    """Time per iteration vs instances, dense vs adaptive (residual dashed), one panel per ray count."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rays = sorted({c["rays"] for c in cases})
    fig, axes = plt.subplots(1, len(rays), figsize=(4.2 * len(rays), 3.8), sharey=True, squeeze=False)
    colours = {"dense": "tab:red", "adaptive": "tab:blue"}
    for ax, n_rays in zip(axes[0], rays):
        for residual in sorted({c["residual"] for c in cases}):
            sel = sorted((c for c in cases if c["rays"] == n_rays and c["residual"] == residual),
                         key=lambda c: c["instances"])
            x = [c["instances"] for c in sel]
            for s in SAMPLINGS:
                ax.plot(x, [c[s]["iter_s_median"] for c in sel], marker="o", color=colours[s],
                        linestyle="--" if residual else "-",
                        label=f"{s}{' + residual' if residual else ''}")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xticks(sorted({c["instances"] for c in cases}))
        ax.get_xaxis().set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.set_xlabel("instances")
        ax.set_title(f"{n_rays} rays")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("forward + backward per iteration (s)")
    axes[0][-1].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def git_commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).resolve().parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def cache_info(fresh: bool) -> dict:
    path = Path(os.environ.get(DRJIT_CACHE_ENV) or Path.home() / ".drjit")
    files = sum(1 for _ in path.glob("*")) if path.is_dir() else 0
    note = ("a fresh empty Dr.Jit kernel cache directory (DRJIT_CACHE_DIR): cold times include "
            "compiling every kernel" if fresh else
            f"the on-disk kernel cache {path} held {files} files at the start, so 'cold' first "
            "iterations may be partly warm (kernels loaded from disk are counted in "
            "cold_kernels.from_disk); run with --fresh-cache for truly cold times")
    return {"dir": str(path), "files_at_start": files, "fresh": fresh, "note": note}


def summary(cases: list[dict]) -> dict:
    """The target case and the worst kernel-compilation count after warm-up."""
    out = {"target": f"adaptive >= {TARGET_SPEEDUP:g}x dense at {TARGET_CASE[0]} instances / "
                     f"{TARGET_CASE[1]} rays"}
    for c in cases:
        if (c["instances"], c["rays"]) == TARGET_CASE:
            key = "with_residual" if c["residual"] else "no_residual"
            out[key] = {"speedup": c["speedup"], "dense_s": c["dense"]["iter_s_median"],
                        "adaptive_s": c["adaptive"]["iter_s_median"], "met": c["speedup"] >= TARGET_SPEEDUP}
    for s in SAMPLINGS:
        out[f"{s}_max_compiles_per_iter_after_warmup"] = max(
            max(c[s]["compiles_per_iter_after_warmup"]) for c in cases)
    return out


def write_outputs(json_path: Path, doc: dict) -> None:
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(doc, indent=1) + "\n")
    write_csv(json_path.with_suffix(".csv"), doc["cases"])
    write_plot(json_path.with_suffix(".png"), doc["cases"],
               f"vsrd_silhouette, s = {doc['config']['sharpness']:g}, {doc['machine']['cpus']} CPUs"
               f"{' (quick)' if doc['quick'] else ''}")


# ----------------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------------


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "integrator", help="vsrd_silhouette: dense vs adaptive time, compilations and accuracy",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", type=Path, default=None, metavar="PATH",
                   help="write results to PATH, plus PATH with .csv and .png suffixes")
    p.add_argument("--quick", action="store_true",
                   help=f"subset: instances {QUICK.instances}, rays {QUICK.rays}")
    p.add_argument("--fresh-cache", action="store_true",
                   help="run in a child process with an empty temporary Dr.Jit kernel cache "
                        "(truly cold first iterations; every kernel compiles once)")
    p.add_argument("--note", default="", help="free text stored in the JSON 'note'")
    p.set_defaults(func=main)


def rerun_with_fresh_cache(args: argparse.Namespace) -> int:
    """Run this command again in a child process whose Dr.Jit cache is an empty temporary folder
    (Dr.Jit reads ``DRJIT_CACHE_DIR`` once, when it starts)."""
    argv = [sys.executable, "-m", "vsrd_mi", "bench", "integrator", "--fresh-cache", "--note", args.note]
    if args.json is not None:
        argv += ["--json", str(args.json)]
    if args.quick:
        argv.append("--quick")
    with tempfile.TemporaryDirectory(prefix="vsrd-bench-drjit-") as tmp:
        env = {**os.environ, DRJIT_CACHE_ENV: tmp, FRESH_CACHE_CHILD: "1"}
        return subprocess.run(argv, env=env).returncode


def main(args: argparse.Namespace) -> int:
    if args.fresh_cache and not os.environ.get(FRESH_CACHE_CHILD):
        return rerun_with_fresh_cache(args)
    cfg = QUICK if args.quick else BenchConfig()
    print(f"vsrd-mi bench integrator{' --quick' if args.quick else ''}: instances {cfg.instances}, "
          f"rays {cfg.rays}, residual {cfg.residual}, s = {cfg.sharpness:g}", flush=True)
    cache = cache_info(bool(args.fresh_cache))
    print(f"  kernel cache: {cache['note']}", flush=True)
    load_start = os.getloadavg()
    start = time.perf_counter()
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    cases = run_benchmark(cfg, log)
    note = args.note
    if args.quick:
        note = (f"--quick subset (instances {cfg.instances}, rays {cfg.rays}). " + note).strip()
    doc = {
        "benchmark": "vsrd-mi bench integrator",
        "command": "vsrd-mi bench integrator" + (" --quick" if args.quick else "")
                   + (" --fresh-cache" if args.fresh_cache else ""),
        "quick": bool(args.quick),
        "note": note,
        "git_commit": git_commit(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "processor": platform.processor(), "loadavg_start": load_start,
                    "loadavg_end": os.getloadavg()},
        "versions": {"drjit": dr.__version__, "mitsuba": mi.__version__, "variant": mi.variant()},
        "jit": {"expand_threshold": dr.expand_threshold(),
                "packet_ops": bool(dr.flag(dr.JitFlag.PacketOps)),
                "scatter_reduce_local": bool(dr.flag(dr.JitFlag.ScatterReduceLocal))},
        "kernel_cache": cache,
        "wall_s": time.perf_counter() - start,
        "config": dataclasses.asdict(cfg),
        "summary": summary(cases),
        "cases": cases,
    }
    print(f"{'inst':>4} {'rays':>6} {'res':>5} {'dense s':>8} {'adapt s':>8} {'speedup':>7} "
          f"{'maxdiff':>7} {'gradcos':>7} {'ad-ref p99':>10} {'de-ref max':>10}")
    for c in cases:
        acc = c["accuracy"]
        print(f"{c['instances']:4d} {c['rays']:6d} {str(c['residual']):>5} {c['dense']['iter_s_median']:8.3f} "
              f"{c['adaptive']['iter_s_median']:8.3f} {c['speedup']:7.1f} {c['max_abs_diff']:7.3f} "
              f"{c['grad_cosine']:7.3f} {acc['adaptive_vs_reference']['p99_abs']:10.4f} "
              f"{acc['dense_vs_reference']['max_abs']:10.3f}")
    print("summary:", json.dumps(doc["summary"]))
    if args.json is not None:
        write_outputs(args.json, doc)
        print(f"wrote {args.json} and its .csv / .png")
    return 0
