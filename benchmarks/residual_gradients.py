"""The residual MLP's two gradient paths side by side: forward + backward step time of the
integrator benchmark's scenes with ``residual_gradients`` = ``fused`` (hand-written derivatives
around one cooperative-vector kernel, :class:`vsrd_plugins.sdf._FusedResidual`) and ``tensor``
(Dr.Jit AD through tensor-mode matmuls), for both samplers, timed in turn in one loop (median
of ``--steps`` steps each, after two warm-up steps); labels and box gradients of the two paths
are compared as well. Then the product's case, where the MLP's weights are differentiated too:
the bundled example's target (``vsrd-mi autolabel`` defaults with the residual field on), run
with each path in turn (``--autolabel-runs`` times, alternating), the median time of a
residual step (after the box-only warm-up) per path.

The dense sampler evaluates the residual at ~20x the adaptive sampler's points, so a faster MLP
shortens its step more: the adaptive-vs-dense ratio of ``vsrd-mi bench integrator`` falls
although both samplers get faster. Both ratios are printed.

Usage::

    python benchmarks/residual_gradients.py --out benchmarks/residual_gradients.json
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import mitsuba as mi
import numpy as np

from common import BUNDLED, side_by_side_steps, write_results
import vsrd_mi  # noqa: F401  (sets the variant, registers the plugins)
from vsrd_mi.bench import integrator as bench
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.data.selection import SelectionConfig, spec_for_frame
from vsrd_mi.data.observations import load_observations
from vsrd_mi.autolabel.job import initial_boxes
from vsrd_mi.optimise.config import default_config
from vsrd_mi.optimise.optimiser import BoxOptimiser

#: The bundled example's target frame (``scripts/run.sh example``).
EXAMPLE_FRAME = 14

#: (instances, rays) cases timed by default: the issue's target case, more boxes, the product's rays.
CASES = ((6, 16384), (12, 16384), (6, 1024))
MODES = ("tensor", "fused")
SAMPLERS = ("adaptive", "dense")


def run_case(n_inst: int, n_rays: int, steps: int, samplers, cfg: bench.BenchConfig) -> dict:
    data, _ = bench.case_data(cfg, n_inst, True)
    batch = data.batch(n_rays)
    runs, agreement = {}, {}
    for sampler in samplers:
        outputs = {}
        for mode in MODES:
            desc = {**bench.integrator_description(data.boxes, sampler, True, cfg), "residual_gradients": mode}
            run = bench.TimedIntegrator(mi.load_dict(desc), batch, cfg, 1)
            render = lambda it=run.it: it.render_rays(batch.o, batch.d, batch.time)  # noqa: E731
            outputs[mode] = bench.labels_and_gradient(run.it, [(render, batch.weights)])
            runs[(sampler, mode)] = run
        (v_t, g_t), (v_f, g_f) = outputs["tensor"], outputs["fused"]
        agreement[sampler] = {"labels_max_abs_diff": float(np.abs(v_t - v_f).max()),
                              "box_grad_cosine": bench.cosine(g_t, g_f)}
    times = side_by_side_steps(runs, steps)
    median = {f"{s}/{m}": float(np.median(t)) for (s, m), t in times.items()}
    out = {"instances": n_inst, "rays": n_rays, "median_s": median,
           "steps_s": {f"{s}/{m}": t for (s, m), t in times.items()}, "agreement": agreement,
           "fused_speedup": {s: median[f"{s}/tensor"] / median[f"{s}/fused"] for s in samplers}}
    if len(samplers) == 2:
        out["adaptive_vs_dense"] = {m: median[f"dense/{m}"] / median[f"adaptive/{m}"] for m in MODES}
    return out


def residual_step_times(mode: str, residual_steps: int) -> list[float]:
    """Seconds of each residual step of the bundled target's optimisation with ``mode``."""
    cfg = default_config().replace(residual=True, residual_gradients=mode)
    cfg = cfg.replace(steps=cfg.warmup_steps + residual_steps,
                      early_stop=dataclasses.replace(cfg.early_stop, enabled=False))
    seq = Sequence(BUNDLED, 0)
    spec = spec_for_frame(seq, EXAMPLE_FRAME, SelectionConfig())
    obs = load_observations(seq, spec)
    start, init_ref, _ = initial_boxes(seq, spec, obs, cfg)
    stamps = []
    BoxOptimiser(obs, start, cfg, init_boxes=init_ref).run(progress=lambda step, loss: stamps.append(time.perf_counter()))
    # the first residual step compiles
    return np.diff(stamps)[cfg.warmup_steps:].tolist()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=7, help="timed steps per sampler, path and case")
    parser.add_argument("--cases", default=",".join(f"{k}x{n}" for k, n in CASES),
                        help="instances x rays per case, comma-separated (default: %(default)s)")
    parser.add_argument("--samplers", default=",".join(SAMPLERS), help="default: %(default)s")
    parser.add_argument("--autolabel-runs", type=int, default=2, help="runs per path of the bundled target (0: skip)")
    parser.add_argument("--autolabel-steps", type=int, default=40, help="residual steps per run")
    parser.add_argument("--out", type=Path, help="write the results as JSON here")
    args = parser.parse_args()
    start = time.perf_counter()
    cfg = bench.BenchConfig()
    samplers = tuple(args.samplers.split(","))
    cases = []
    for n_inst, n_rays in (map(int, c.split("x")) for c in args.cases.split(",")):
        case = run_case(n_inst, n_rays, args.steps, samplers, cfg)
        cases.append(case)
        m = case["median_s"]
        line = ", ".join(f"{s} tensor {m[f'{s}/tensor']:.3f} s / fused {m[f'{s}/fused']:.3f} s "
                         f"({case['fused_speedup'][s]:.2f}x; labels {case['agreement'][s]['labels_max_abs_diff']:.1e}, "
                         f"grad cos {case['agreement'][s]['box_grad_cosine']:.6f})" for s in samplers)
        if "adaptive_vs_dense" in case:
            r = case["adaptive_vs_dense"]
            line += f"; adaptive vs dense: tensor {r['tensor']:.2f}x, fused {r['fused']:.2f}x"
        print(f"{n_inst:2d} boxes {n_rays:6d} rays: {line}", flush=True)
    autolabel = None
    if args.autolabel_runs:
        steps = {mode: [] for mode in MODES}
        for _ in range(args.autolabel_runs):
            for mode in MODES:
                steps[mode] += residual_step_times(mode, args.autolabel_steps)
        median = {mode: float(np.median(t)) for mode, t in steps.items()}
        autolabel = {"frame": EXAMPLE_FRAME, "median_residual_step_s": median, "residual_steps_s": steps,
                     "fused_speedup": median["tensor"] / median["fused"]}
        print(f"autolabel (bundled target, residual on): tensor {median['tensor']:.3f} s / fused "
              f"{median['fused']:.3f} s per residual step ({autolabel['fused_speedup']:.2f}x)", flush=True)
    if args.out:
        write_results(args.out, __doc__, time.perf_counter() - start, head=bench.git_commit(), cases=cases,
                      autolabel=autolabel)
        plot(args.out.with_suffix(".png"), cases, autolabel)


def plot(path: Path, cases: list[dict], autolabel: dict | None) -> None:
    """Bars: median step time per case and sampler (and the autolabel residual step), per path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels, values = [], {mode: [] for mode in MODES}
    for case in cases:
        for key in case["median_s"]:
            sampler, mode = key.split("/")
            if mode == MODES[0]:
                labels.append(f"{sampler}\n{case['instances']} boxes\n{case['rays']} rays")
            values[mode].append(case["median_s"][key])
    if autolabel:
        labels.append("autolabel\nresidual step\n(bundled)")
        for mode in MODES:
            values[mode].append(autolabel["median_residual_step_s"][mode])
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(labels)), 4.0))
    for i, mode in enumerate(MODES):
        ax.bar(x + (i - 0.5) * 0.38, values[mode], 0.38, label=f"residual_gradients={mode}")
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("forward + backward step (s, median)")
    ax.set_title("Residual MLP gradients: fused vs tensor mode (side by side, one process)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
