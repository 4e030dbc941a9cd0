"""``vsrd-mi bench integrator-features``: what each feature of the adaptive sampler buys, side by side.

On the integrator benchmark's scenes (``vsrd-mi bench integrator``: same seeds and rays, s = 10)
the adaptive sampler runs as it ships and with one feature switched off at a time
(:data:`SETTINGS`; internal settings of :class:`~vsrd_plugins.silhouette.settings.SilhouetteSettings`),
next to the dense sampler. Per setting and case (instances x rays):

* the forward + backward step time, every setting timed in turn in one loop (median of
  ``--steps`` steps after two warm-up steps each: load from other processes hits all alike;
  compare the ratios, not the seconds), and its ratio to the default's;
* the soft labels' error against the converged reference (the integrator's integral on a fine
  grid plus every box's deepest point, :func:`~vsrd_mi.bench.measure.reference_chunks`) on the
  first ``--accuracy-rays`` rays: max and 99th percentile over rays of the largest error over
  instances; and the cosine of the gradient w.r.t. the box parameters on the first
  ``--fd-rays`` rays with central differences of the reference (the derivative of the
  converged integral).

A feature is kept where switching it off costs 10 % or more of step time, or where the labels
then leave the 0.01 bound of the reference (``docs/integrators.md``, "What each feature buys").
Outputs: ``--out`` (JSON) and a PNG of the step-time ratios next to it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr

from .measure import (TimedIntegrator, cosine, label_error, labels_and_gradient, reference_chunks,
                      reference_fd_gradient, side_by_side_steps, write_results)
from .scenes import BenchConfig, CaseData, case_data, load_integrator

#: (name, sampling, residual field, settings changed): the runs compared, per residual on / off.
SETTINGS = (
    ("dense", "dense", True, {}),
    ("adaptive (default)", "adaptive", True, {}),
    ("no isolated-ray layout", "adaptive", True, {"isolated_rays": False}),
    ("no residual lattice", "adaptive", True, {"residual_lattice": 0.0}),
    ("no chord grid (exact residual)", "adaptive", True, {"residual_grid": 0.0}),
    ("tensor-mode residual gradients", "adaptive", True, {"residual_gradients": "tensor"}),
    ("no moved samples", "adaptive", True, {"residual_tail_scan": 0}),
    ("no tail samples", "adaptive", True, {"residual_tail": 0}),
    ("no residual search", "adaptive", True, {"residual_tail": 0, "residual_scan": 0}),
    ("no ridge gradients", "adaptive", True, {"ridge_gradients": False}),
    ("box only: dense", "dense", False, {}),
    ("box only: adaptive (default)", "adaptive", False, {}),
    ("box only: no isolated-ray layout", "adaptive", False, {"isolated_rays": False}),
)
#: The bounds a setting must keep to stand in for the default (adaptive vs the reference).
LABEL_BOUND = 0.01
GRAD_COSINE_MIN = 0.99
#: A feature is worth keeping where switching it off slows a step by at least this factor.
WORTH = 1.1


def accuracy(data: dict[bool, CaseData], n: int, fd_rays: int, cfg: BenchConfig) -> dict[str, dict]:
    """Per setting: the label error against the reference on the first ``n`` rays, and the cosine
    of its box gradient on the first ``fd_rays`` rays with central differences of the reference
    (the derivative of the converged integral; the reference's own AD gradient is one-sided at
    the deepest samples inside boxes, :mod:`~vsrd_mi.bench.measure`)."""
    refs, fds = {}, {}
    for residual, case in data.items():
        it = load_integrator(case.boxes, "dense", residual, cfg)
        with dr.suspend_grad():
            refs[residual] = np.concatenate([np.stack([np.array(x) for x in render()[:it.field.n]], 0)
                                             for render, _ in reference_chunks(it, case, n, cfg)], axis=1)
        fds[residual] = reference_fd_gradient(case, residual, fd_rays, cfg)
    out = {}
    for name, sampling, residual, settings in SETTINGS:
        case = data[residual]
        it = load_integrator(case.boxes, sampling, residual, cfg, **settings)
        batch, fd_batch = case.batch(n), case.batch(fd_rays)
        with dr.suspend_grad():
            labels = np.stack([np.array(x) for x in it.render_rays(batch.o, batch.d, batch.time)[:it.field.n]])
        grad = labels_and_gradient(it, iter([(lambda it=it: it.render_rays(fd_batch.o, fd_batch.d, fd_batch.time),
                                              fd_batch.weights)]))[1]
        err = label_error(labels, refs[residual])
        cos = cosine(grad, fds[residual])
        out[name] = {**err, "grad_cosine_vs_reference_fd": cos,
                     "within_bounds": bool(err["max_abs"] <= LABEL_BOUND and cos >= GRAD_COSINE_MIN)}
        print(f"  {name:34s} max {err['max_abs']:.4f} p99 {err['p99_abs']:.4f} cos {cos:.4f}", flush=True)
    return out


def timing(data: dict[bool, CaseData], n_rays: int, steps: int, cfg: BenchConfig) -> dict[str, dict]:
    """Median step time of every setting, timed side by side; ratios to the defaults."""
    runs = {name: TimedIntegrator(load_integrator(data[residual].boxes, sampling, residual, cfg, **settings),
                                  data[residual].batch(n_rays), cfg, seed=1)
            for name, sampling, residual, settings in SETTINGS}
    seconds = side_by_side_steps(runs, steps)
    median = {name: float(np.median(v)) for name, v in seconds.items()}
    out = {}
    for name, _, residual, _ in SETTINGS:
        default = median["adaptive (default)" if residual else "box only: adaptive (default)"]
        out[name] = {"median_s": median[name], "steps_s": seconds[name], "vs_default": median[name] / default}
        print(f"  {name:34s} {median[name]:7.3f} s  {out[name]['vs_default']:5.2f}x the default", flush=True)
    return out


def write_plot(path: Path, cases: list[dict]) -> None:
    """Step time of each setting relative to its default, one bar group per case."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [name for name, sampling, _, _ in SETTINGS if sampling == "adaptive"]
    fig, ax = plt.subplots(figsize=(9, 0.35 * len(names) + 1.5))
    y = np.arange(len(names))
    height = 0.8 / len(cases)
    for i, case in enumerate(cases):
        ax.barh(y + i * height, [case["timing"][n]["vs_default"] for n in names], height,
                label=f"{case['instances']} boxes, {case['rays']} rays")
    ax.axvline(1.0, color="k", lw=0.8)
    ax.axvline(WORTH, color="C3", ls="--", lw=0.8, label=f"{WORTH:g}x: worth keeping")
    ax.set_yticks(y + 0.4 - height / 2, names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("step time / the default's (side by side)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def register(subparsers) -> None:
    p = subparsers.add_parser("integrator-features", help="vsrd_silhouette: each sampler feature switched off, "
                                                          "side by side (time and accuracy)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--instances", type=int, nargs="+", default=[6, 12])
    p.add_argument("--rays", type=int, default=16384)
    p.add_argument("--steps", type=int, default=7, help="timed steps per setting (after two warm-up steps)")
    p.add_argument("--accuracy-rays", type=int, default=512)
    p.add_argument("--fd-rays", type=int, default=128, help="rays of the gradient check (2 reference renders per "
                                                          "box parameter)")
    p.add_argument("--out", type=Path, default=Path("benchmarks/integrator_features.json"))
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    cfg = BenchConfig()
    start = time.perf_counter()
    cases = []
    for n_inst in args.instances:
        data = {residual: case_data(cfg, n_inst, residual)[0] for residual in (False, True)}
        print(f"{n_inst} boxes: accuracy on {args.accuracy_rays} rays", flush=True)
        acc = accuracy(data, args.accuracy_rays, args.fd_rays, cfg)
        print(f"{n_inst} boxes, {args.rays} rays: step times side by side", flush=True)
        cases.append({"instances": n_inst, "rays": args.rays, "accuracy": acc,
                      "timing": timing(data, args.rays, args.steps, cfg)})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_results(args.out, __doc__, time.perf_counter() - start, settings=[
        {"name": n, "sampling": s, "residual": r, "changed": c} for n, s, r, c in SETTINGS],
        bounds={"label": LABEL_BOUND, "grad_cosine": GRAD_COSINE_MIN, "worth": WORTH}, cases=cases)
    write_plot(args.out.with_suffix(".png"), cases)
    print(f"wrote {args.out} and its .png")
    return 0
