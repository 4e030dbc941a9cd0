"""``vsrd-mi bench residual-trained``: does the adaptive sampler keep the issue's bounds on a residual field that has been trained? Per target of the bundled scene, the field after ``vsrd-mi autolabel --set residual=true`` against the same boxes with the untrained field, labels and gradients against the converged reference.

The integrator tests and ``residual_scenes.py`` measure the sampler on residual fields at their
initialisation (random hypernetwork weights). In use the field is trained on the masks, and a
trained field may bend ``B + R`` more along a ray (more extrema, steeper slopes) than an
untrained one. Per target frame of the bundled scene this script runs the default optimisation
with the residual field on (``AutolabelConfig(residual=True)``: 600 steps, the field from step
200), then, with the optimised boxes and

* ``trained``: the optimised field, and
* ``untrained``: the field's initial weights (same seed),

renders rays drawn like the training rays (the optimiser's :class:`RaySampler` over the target
and its source frames) at the schedule's sharpness values ``s`` (``tau = 1/s``) with the adaptive
sampler, with the paper's dense sampler (``dense_*`` keys, for scale) and with the converged
reference (the NeuS integral on a uniform grid of spacing
``min(0.05/s, 5 mm)`` over each ray's stretch through the boxes enlarged by the culling
margin, plus every box's deepest point; outside that stretch every box's SDF exceeds the
margin). Per case: the largest and 99th-percentile label error, and, at the final sharpness,
the cosine between the adaptive gradient and the reference's of a random-weighted sum of the
labels w.r.t. the box parameters and w.r.t. the residual field's parameters.

Usage::

    vsrd-mi bench residual-trained --frames 8 14 20 --out benchmarks/residual_trained.json
    vsrd-mi bench residual-trained --save-states runs/trained   # keep the trained fields
    vsrd-mi bench residual-trained --load-states runs/trained   # a sampler change, same fields
"""

from __future__ import annotations

import argparse
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np

import drjit as dr
import mitsuba as mi

from ..autolabel.job import initial_boxes
from ..data.kitti360 import Sequence, sequence_name
from ..data.observations import load_observations
from ..data.selection import SelectionConfig, spec_for_frame
from ..optimise.config import PRESETS
from ..optimise.optimiser import BoxOptimiser, RaySampler
from .measure import central_differences, cosine, fd_steps, labels_and_gradient, reference_grid, weighted_loss, write_results
from .scenes import BenchConfig, FDSteps

#: The bounds (adaptive vs the converged integral).
LABEL_BOUND = 0.01
GRAD_COSINE_MIN = 0.99
#: Reference grid spacing: this fraction of 1/s, at most REF_SPACING_MAX_M (as the tests).
REF_SPACING_S = 0.05
REF_SPACING_MAX_M = 0.005
#: Central differences of the box parameters move the surfaces by this much (m): a label can bend
#: within 3 cm at s = 10.
FD_SURFACE_M = 0.001
#: Reference samples per chunk of rays (memory of the reference's backward pass).
REF_CHUNK_SAMPLES = 1 << 20
#: The bundled example scene (relative to the working directory, as the CLI's other commands).
BUNDLED = Path("scenes/kitti360-synth")


def ray_stretches(boxes: dict, o: np.ndarray, d: np.ndarray, t: np.ndarray, margin: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per ray the first entry into and the last exit from any box enlarged by ``margin``
    (slab tests in each box's frame; dynamic boxes at the ray time). Rays that meet none get
    an empty stretch ``[0, 0]``."""
    c, s = np.cos(boxes["yaw"]), np.sin(boxes["yaw"])
    centre = boxes["centre"][None] + (boxes["dynamic"][:, None] * boxes["velocity"])[None] * t[:, None, None]
    half = 0.5 * boxes["size"][None] + margin
    q, v = o[:, None] - centre, np.broadcast_to(d[:, None], centre.shape)

    def local(x):
        return np.stack([c * x[..., 0] - s * x[..., 2], x[..., 1], s * x[..., 0] + c * x[..., 2]], -1)

    ql, vl = local(q), local(v)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / vl
        a, b = (-half - ql) * inv, (half - ql) * inv
    lo = np.nanmax(np.minimum(a, b), axis=-1).clip(min=0.0)
    hi = np.nanmin(np.maximum(a, b), axis=-1)
    hit = hi > lo
    first = np.where(hit, lo, np.inf).min(axis=1)
    last = np.where(hit, hi, -np.inf).max(axis=1)
    met = np.isfinite(first)
    return np.where(met, first, 0.0), np.where(met, last, 0.0)


def reference_render(it, rays: tuple[np.ndarray, ...], s: float, margin: float):
    """``(render, m)``: a function rendering the reference labels of rays ``a:b`` of ``rays``
    (NumPy ``o, d, t``) at the integrator's current boxes, and the samples per ray: a grid of
    spacing ``min(REF_SPACING_S / s, REF_SPACING_MAX_M)`` over each ray's :func:`ray_stretches`
    plus every box's deepest point (:func:`reference_grid`)."""
    o, d, t = rays
    boxes = it.boxes()
    lo, hi = ray_stretches(boxes, o, d, t, margin)
    m = int(np.ceil((hi - lo).max() / min(REF_SPACING_S / s, REF_SPACING_MAX_M))) + 2

    def render(a: int, b: int) -> list[mi.Float]:
        ts, mm = reference_grid(boxes, o[a:b], d[a:b], t[a:b], hi[a:b], m, near=lo[a:b])
        return it.integrate_at(it.field.decode(), dr.arange(mi.UInt32, b - a),
                               *mi_of(tuple(x[a:b] for x in rays)), ts, mm)

    return render, m + len(boxes["yaw"])


def labels_of(render, n_rays: int, chunk: int, n_inst: int) -> np.ndarray:
    """``(n_inst, n_rays)`` labels of ``render(a, b)`` (rays ``a:b``), ``chunk`` rays at a time."""
    with dr.suspend_grad():
        out = []
        for a in range(0, n_rays, chunk):
            out.append(np.stack([np.array(x) for x in render(a, min(a + chunk, n_rays))[:n_inst]]))
    return np.concatenate(out, axis=1)


def residual_gradient(it, render, n_rays: int, chunk: int, weights: np.ndarray) -> np.ndarray:
    """Gradient of ``sum weights * labels`` (rendered chunk by chunk, accumulated) w.r.t. the
    residual field's parameters."""
    params = dict(it.field.residual.params)
    for v in params.values():
        dr.enable_grad(v)
        dr.clear_grad(v)
    for a in range(0, n_rays, chunk):
        b = min(a + chunk, n_rays)
        dr.backward(weighted_loss(render(a, b)[:it.field.n], mi_weights(weights[:, a:b])))
    out = np.concatenate([np.array(dr.grad(v)) for v in params.values()])
    for v in params.values():
        dr.disable_grad(v)
    return out


def mi_weights(weights: np.ndarray) -> list[mi.Float]:
    """Per instance its row of loss weights as a Dr.Jit array."""
    return [mi.Float(w.astype(np.float32)) for w in weights]


@contextmanager
def sampler(it, sampling: str):
    """The integrator with its sampling strategy switched to ``sampling`` for a while."""
    settings = it.settings
    it.settings = replace(settings, sampling=sampling)
    try:
        yield it
    finally:
        it.settings = settings


def mi_of(rays: tuple[np.ndarray, ...]) -> tuple[mi.Point3f, mi.Vector3f, mi.Float]:
    o, d, t = rays
    return (mi.Point3f(np.ascontiguousarray(o.T, dtype=np.float32)),
            mi.Vector3f(np.ascontiguousarray(d.T, dtype=np.float32)), mi.Float(t.astype(np.float32)))


def measure(it, rays, sharpness: list[float], grad_rays: int, seed: int) -> list[dict]:
    o, d, t = rays
    n_rays, n_inst = len(o), it.field.n
    mi_rays = mi_of(rays)
    grad_rays = min(grad_rays, n_rays)
    rows = []
    for s in sharpness:
        it.set_schedule(s, 1.0 / s)
        margin = float(it.context().cull_margin()[0])
        ref_render, m = reference_render(it, rays, s, margin)
        chunk = max(1, REF_CHUNK_SAMPLES // m)
        ref = labels_of(ref_render, n_rays, chunk, n_inst)
        row = {"sharpness": s, "reference_samples": m, "rays_seeing_a_box": int((ref.sum(0) > 0.5).sum())}
        for sampling in ("adaptive", "dense"):
            with dr.suspend_grad(), sampler(it, sampling):
                labels = np.stack([np.array(x) for x in it.render_rays(*mi_rays)[:n_inst]])
            err = np.abs(labels - ref).max(axis=0)
            prefix = "" if sampling == "adaptive" else "dense_"
            row.update({f"{prefix}max_abs": float(err.max()), f"{prefix}p99_abs": float(np.quantile(err, 0.99)),
                        f"{prefix}rays_above_bound": int((err > LABEL_BOUND).sum())})
        if s == sharpness[-1] and grad_rays:
            # the box gradient against central differences of the converged reference (AD of the
            # reference differentiates its grid samples, which lie near, not at, the minima of
            # B + R); the residual field's (1.2k hypernetwork parameters) against the
            # reference's AD
            w = np.random.default_rng(seed).normal(size=(n_inst, grad_rays))
            sub_rays = tuple(x[:grad_rays] for x in rays)
            sub_render, sub_m = reference_render(it, sub_rays, s, margin)
            sub_chunk = max(1, REF_CHUNK_SAMPLES // sub_m)
            sub = mi_of(sub_rays)

            def reference_loss() -> float:
                render_now = reference_render(it, sub_rays, s, margin)[0]
                return float((labels_of(render_now, grad_rays, sub_chunk, n_inst) * w).sum())

            fd = central_differences(it, reference_loss, fd_steps(n_inst, BenchConfig(fd=FDSteps(surface_m=FD_SURFACE_M))))
            g_box = labels_and_gradient(it, iter([(lambda: it.render_rays(*sub), mi_weights(w))]))[1]
            g_res_ref = residual_gradient(it, sub_render, grad_rays, sub_chunk, w)
            g_res = residual_gradient(it, lambda a, b: it.render_rays(*sub), grad_rays, grad_rays, w)
            row.update({"grad_cosine_box_vs_fd": cosine(g_box, fd),
                        "grad_cosine_residual_vs_reference_ad": cosine(g_res, g_res_ref)})
        print(f"    s={s:g}: {row}", flush=True)
        rows.append(row)
    return rows


def state_name(frame: int) -> str:
    """File of a target's trained state (``--save-states`` / ``--load-states``)."""
    return f"frame_{frame:04d}.npz"


def run_target(frame: int, args) -> dict:
    seq = Sequence(args.root, sequence_name(0))
    spec = spec_for_frame(seq, frame, SelectionConfig())
    obs = load_observations(seq, spec)
    cfg = PRESETS["default"]().replace(residual=True, steps=args.steps,
                                       warmup_steps=int(args.steps * PRESETS["default"]().warmup_steps
                                                        / PRESETS["default"]().steps))
    start, init_ref, _, surface = initial_boxes(seq, spec, obs, cfg)
    opt = BoxOptimiser(obs, start, cfg, init_boxes=init_ref, surface_points=surface)
    it, residual = opt.integrator, opt.integrator.field.residual
    untrained = {k: np.array(v) for k, v in residual.params.items()}
    state = None if args.load_states is None else np.load(args.load_states / state_name(frame))
    if state is None:
        t0 = time.time()
        steps = opt.run().steps
        print(f"frame {frame}: {obs.num_instances} boxes, {steps} steps in {time.time() - t0:.0f} s", flush=True)
        o, d, t, _ = RaySampler(obs, opt.frames, args.rays, seed=args.seed).sample(opt.perm)
        rays = (np.array(o).T.astype(np.float64), np.array(d).T.astype(np.float64), np.array(t).astype(np.float64))
        boxes = {k: np.array(v) for k, v in it.field.params.items()}  # centre, size, yaw, velocity, dynamic
        trained = {k: np.array(v) for k, v in residual.params.items()}
    else:  # the trained state of an earlier run: the sampler measured on the very same fields
        steps = int(state["steps"])
        rays = (state["o"], state["d"], state["t"])
        boxes = {k[4:]: state[k] for k in state.files if k.startswith("box_")}
        trained = {k[4:]: state[k] for k in state.files if k.startswith("rdf_")}
        print(f"frame {frame}: {obs.num_instances} boxes, state of {args.load_states / state_name(frame)}", flush=True)
    if args.save_states is not None:
        args.save_states.mkdir(parents=True, exist_ok=True)
        np.savez(args.save_states / state_name(frame), steps=steps, o=rays[0], d=rays[1], t=rays[2],
                 **{f"box_{k}": v for k, v in boxes.items()}, **{f"rdf_{k}": v for k, v in trained.items()})
    for k, v in boxes.items():
        it.field.params[k] = mi.Float(v)
    it.field.use_residual = True
    out = {"frame": frame, "boxes": obs.num_instances, "steps": steps, "fields": {}}
    for name, params in (("trained", trained), ("untrained", untrained)):
        residual.params.update({k: mi.Float(v) for k, v in params.items()})
        print(f"  {name} field", flush=True)
        out["fields"][name] = measure(it, rays, args.sharpness, args.grad_rays, args.seed + frame)
    return out


def register(subparsers) -> None:
    ap = subparsers.add_parser("residual-trained", help="vsrd_silhouette on trained residual fields of the bundled "
                                                        "scene against the converged reference",
                               description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=BUNDLED, help="the bundled scene")
    ap.add_argument("--frames", type=int, nargs="+", default=[8, 14, 20], help="target frames of the bundled scene")
    ap.add_argument("--steps", type=int, default=PRESETS["default"]().steps, help="optimisation steps")
    ap.add_argument("--rays", type=int, default=2048, help="training-like rays per target")
    ap.add_argument("--grad-rays", type=int, default=512, help="rays of the gradient comparison (0: none)")
    ap.add_argument("--sharpness", type=float, nargs="+", default=[1.0, 3.0, 10.0],
                    help="sharpness values along the schedule (tau = 1/s); gradients at the last")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save-states", type=Path, help="write each target's trained boxes, field and rays here")
    ap.add_argument("--load-states", type=Path,
                    help="measure on the states an earlier --save-states wrote instead of training (training "
                         "runs are not bit-reproducible: this compares samplers on the same fields)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/residual_trained.json"))
    ap.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    t0 = time.time()
    targets = [run_target(f, args) for f in args.frames]
    summary = summarise(targets, args.sharpness)
    print(summary)
    write_results(args.out, __doc__, time.time() - t0, bound=LABEL_BOUND, grad_cosine_min=GRAD_COSINE_MIN,
                  summary=summary, targets=targets)
    write_plot(args.out.with_suffix(".png"), targets)
    return 0


def summarise(targets: list[dict], sharpness: list[float]) -> dict:
    """Per field (trained, untrained) and sharpness: the worst largest and 99th-percentile
    label error over the targets, adaptive and dense; the least gradient cosines."""
    out = {}
    for name in ("trained", "untrained"):
        rows = [r for tg in targets for r in tg["fields"][name]]
        per_s = {}
        for s in sharpness:
            at = [r for r in rows if r["sharpness"] == s]
            per_s[f"s={s:g}"] = {k: max(r[k] for r in at) for k in
                                 ("max_abs", "p99_abs", "dense_max_abs", "dense_p99_abs")}
        out[name] = {"worst": per_s,
                     "cases_above_bound": sum(r["max_abs"] > LABEL_BOUND for r in rows),
                     "least_grad_cosine": {k: min(r[k] for r in rows if k in r)
                                           for k in ("grad_cosine_box_vs_fd", "grad_cosine_residual_vs_reference_ad")}}
    return out


def write_plot(path: Path, targets: list[dict]) -> None:
    """Largest label error per target and sharpness, adaptive and dense, per field."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, name in zip(axes, ("trained", "untrained")):
        labels, adaptive, dense = [], [], []
        for tg in targets:
            for r in tg["fields"][name]:
                labels.append(f"f{tg['frame']} s={r['sharpness']:g}")
                adaptive.append(r["max_abs"])
                dense.append(r["dense_max_abs"])
        x = np.arange(len(labels))
        ax.bar(x - 0.2, adaptive, 0.4, label="adaptive")
        ax.bar(x + 0.2, dense, 0.4, label="dense (paper)")
        ax.axhline(LABEL_BOUND, color="k", ls="--", lw=0.8, label="bound 0.01")
        ax.set_yscale("log")
        ax.set_xticks(x, labels, rotation=60, fontsize=7)
        ax.set_title(f"{name} residual field")
    axes[0].set_ylabel("largest label error vs converged reference")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
