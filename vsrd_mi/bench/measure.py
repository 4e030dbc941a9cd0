"""Measurement primitives of the integrator benchmarks: kernel counts, side-by-side timing, the
converged reference integral and finite differences.

The reference is the integrator's own NeuS integral (``integrate_at``) on a uniform grid of spacing
``ref_spacing / s`` plus every box's exact deepest point along each ray (:func:`reference_grid`):
it converges to the continuous integral, which the paper's dense 100 + 100 sampler does not
(up to ~0.4 off on grazing rays at s = 10). The AD gradient of any sampled integral, the
reference's included, is one-sided where a ray's deepest sample inside a box lies on a ridge of
the box SDF; central differences of the reference labels (:func:`reference_fd_gradient`) are the
derivative of the converged integral.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from vsrd_plugins.silhouette import VSRDSilhouetteIntegrator

from ..optimise.losses import to_float, to_uint
from .scenes import BOX_KEYS, BenchConfig, CaseData, RayBatch, load_integrator


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
            std = {"centre": cfg.perturbation.centre_m, "size": cfg.perturbation.size_m, "yaw": cfg.perturbation.yaw_rad}
            for k, sigma in std.items():
                it.field.params[k] = to_float(self.base[k] + self.rng.normal(0.0, sigma, self.base[k].shape))
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
    far = float((np.linalg.norm(boxes["centre"], axis=1) + 0.5 * np.linalg.norm(boxes["size"], axis=1)
                 + np.linalg.norm(boxes["velocity"], axis=1) * cfg.scene.max_time).max() + cfg.ref_margin)
    return far, int(np.ceil(far * cfg.sharpness / cfg.ref_spacing))


#: Ternary-search iterations of :func:`deepest_points` (float64; shrinks the bracket by 1.5^-n).
DEEPEST_ITERATIONS = 100


def deepest_points(boxes: dict[str, np.ndarray], o: np.ndarray, d: np.ndarray, time: np.ndarray,
                   t_max: float) -> np.ndarray:
    """``(rays, boxes)`` ray parameters in ``[0, t_max]`` of each box's least SDF along each ray
    (closest approach, or deepest point inside), by float64 ternary search: the exact box SDF is
    convex along a line. Boxes as :meth:`~vsrd_plugins.silhouette.VSRDSilhouetteIntegrator.boxes`
    (dynamic ones at the ray time)."""
    c, s = np.cos(boxes["yaw"]), np.sin(boxes["yaw"])
    centre = boxes["centre"][None] + (boxes["dynamic"][:, None] * boxes["velocity"])[None] * time[:, None, None]
    half = 0.5 * boxes["size"][None]

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
        t, mm = reference_grid(it.boxes(), o, d, tm, far, m)
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


def fd_steps(count: int, cfg: BenchConfig) -> dict[str, np.ndarray]:
    """Per box parameter of ``count`` boxes, the step moving box surfaces by ``cfg.fd.surface_m``:
    the centre by that, the size by twice that (both faces move), the yaw by that over the lever
    of the box corners, the velocity by that over the largest ray time."""
    step = cfg.fd.surface_m
    return {"centre": np.full(3 * count, step), "size": np.full(3 * count, 2.0 * step),
            "yaw": np.full(count, step / cfg.fd.yaw_lever_m), "velocity": np.full(3 * count, step / cfg.scene.max_time)}


def reference_fd_gradient(data: CaseData, residual: bool, n: int, cfg: BenchConfig) -> np.ndarray:
    """Central differences of :func:`weighted_loss` of the reference labels of the first ``n`` rays
    w.r.t. every box parameter (steps :func:`fd_steps`), in the order of :data:`BOX_KEYS`.

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

    return central_differences(it, loss, fd_steps(it.field.n, cfg))


def central_differences(it: VSRDSilhouetteIntegrator, loss: Callable[[], float],
                        steps: dict[str, np.ndarray]) -> np.ndarray:
    """Central differences of ``loss()`` w.r.t. every box parameter of ``it`` (in the order
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


def side_by_side_steps(runs: dict, steps: int, warmup: int = 2) -> dict[object, list[float]]:
    """Seconds of ``steps`` steps of each of ``runs`` (objects with ``step() -> (seconds, ...)``,
    e.g. :class:`TimedIntegrator`), timed in turn in one loop after ``warmup`` steps each (the
    second call's layouts can compile too): a noisy machine then slows every run alike."""
    for run in runs.values():
        for _ in range(warmup):
            run.step()
    times = {key: [] for key in runs}
    for _ in range(steps):
        for key, run in runs.items():
            times[key].append(run.step()[0])
    return times


#: Reference grid spacing of :func:`reference_labels` as a fraction of ``1/s``, and at most this
#: many metres: the derivative of a sampled integral also depends on where samples fall relative
#: to the SDF's kinks (box edges, the crossing of two boxes' distances), which are sharp at any s.
REF_SPACING_S, REF_SPACING_MAX_M = 0.05, 0.005
#: The reference's stretch runs this far (m) beyond the farthest box, plus three frames of motion.
REF_MARGIN_M, REF_MOTION_FRAMES = 2.0, 3.0


def reference_labels(it: VSRDSilhouetteIntegrator, scene: dict, rays, s: float) -> list[mi.Float]:
    """The tests' converged reference: the integral on a uniform grid over ``[0, beyond the
    farthest box]`` (spacing ``REF_SPACING_S / s``, at most ``REF_SPACING_MAX_M``) plus each box's
    deepest point along each ray (at the integrator's current boxes)."""
    o, d, t = rays
    n = dr.width(o.x)
    reach = np.linalg.norm(scene["centre"], axis=1) + np.linalg.norm(scene["size"], axis=1)
    reach += np.abs(scene["velocity"]).sum(1) * REF_MOTION_FRAMES + REF_MARGIN_M
    t_max = float(reach.max())
    m = int(np.ceil(t_max / min(REF_SPACING_S / s, REF_SPACING_MAX_M)))
    grid, mm = reference_grid(it.boxes(), np.array(o).T.astype(np.float64), np.array(d).T.astype(np.float64),
                              np.array(t, dtype=np.float64), t_max, m)
    return it.integrate_at(it.field.decode(), dr.arange(mi.UInt32, n), o, d, t, grid, mm)


def write_results(path: Path, doc: str | None, elapsed: float, **fields) -> None:
    """A benchmark's results as JSON: its purpose (the first paragraph of ``doc``), the command
    line, the elapsed seconds and ``fields``."""
    path.write_text(json.dumps({"purpose": (doc or "").split("\n\n")[0], "command": " ".join(["vsrd-mi"] + sys.argv[1:]),
                                "elapsed_seconds": elapsed, **fields}, indent=1) + "\n")
