"""The residual MLP's two gradient paths side by side: forward + backward step time of the
integrator benchmark's scenes with ``residual_gradients`` = ``fused`` (hand-written derivatives
around one cooperative-vector kernel, :class:`vsrd_plugins.sdf._FusedResidual`) and ``tensor``
(Dr.Jit AD through tensor-mode matmuls), for both samplers, timed in turn in one loop (median
of ``--steps`` steps each, after two warm-up steps); labels and box gradients of the two paths
are compared as well.

The dense sampler evaluates the residual at ~20x the adaptive sampler's points, so a faster MLP
shortens its step more: the adaptive-vs-dense ratio of ``vsrd-mi bench integrator`` falls
although both samplers get faster. Both ratios are printed.

Usage::

    python benchmarks/residual_gradients.py --out benchmarks/residual_gradients.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from common import write_results
import vsrd_mi  # noqa: F401  (sets the variant, registers the plugins)
from vsrd_mi.bench import integrator as bench

#: (instances, rays) cases timed by default: the issue's target case, more boxes, the product's rays.
CASES = ((6, 16384), (12, 16384), (6, 1024))
MODES = ("tensor", "fused")
SAMPLERS = ("adaptive", "dense")


def box_gradient(it, batch: bench.RayBatch) -> np.ndarray:
    """Labels and the weighted loss's gradient w.r.t. the box parameters (one pass)."""
    params = [it.field.params[k] for k in bench.BOX_KEYS]
    for p in params:
        dr.enable_grad(p)
    labels = it.render_rays(batch.o, batch.d, batch.time)
    dr.backward(bench.weighted_loss(labels[:it.field.n], batch.weights))
    grad = np.concatenate([np.array(dr.grad(p)) for p in params])
    values = np.stack([np.array(dr.detach(x)) for x in labels])
    for k, p in zip(bench.BOX_KEYS, params):
        it.field.params[k] = dr.detach(p)
    return values, grad


def run_case(n_inst: int, n_rays: int, steps: int, samplers, cfg: bench.BenchConfig) -> dict:
    data, _ = bench.case_data(cfg, n_inst, True)
    batch = data.batch(n_rays)
    runs, agreement = {}, {}
    for sampler in samplers:
        outputs = {}
        for mode in MODES:
            desc = {**bench.integrator_description(data.boxes, sampler, True, cfg), "residual_gradients": mode}
            run = bench.TimedIntegrator(mi.load_dict(desc), batch, cfg, 1)
            outputs[mode] = box_gradient(run.it, batch)
            run.step()
            run.step()
            runs[(sampler, mode)] = run
        (v_t, g_t), (v_f, g_f) = outputs["tensor"], outputs["fused"]
        agreement[sampler] = {"labels_max_abs_diff": float(np.abs(v_t - v_f).max()),
                              "box_grad_cosine": bench.cosine(g_t, g_f)}
    times = {key: [] for key in runs}
    for _ in range(steps):
        for key, run in runs.items():
            times[key].append(run.step()[0])
    median = {f"{s}/{m}": float(np.median(t)) for (s, m), t in times.items()}
    out = {"instances": n_inst, "rays": n_rays, "median_s": median,
           "steps_s": {f"{s}/{m}": t for (s, m), t in times.items()}, "agreement": agreement,
           "fused_speedup": {s: median[f"{s}/tensor"] / median[f"{s}/fused"] for s in samplers}}
    if len(samplers) == 2:
        out["adaptive_vs_dense"] = {m: median[f"dense/{m}"] / median[f"adaptive/{m}"] for m in MODES}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=7, help="timed steps per sampler, path and case")
    parser.add_argument("--cases", default=",".join(f"{k}x{n}" for k, n in CASES),
                        help="instances x rays per case, comma-separated (default: %(default)s)")
    parser.add_argument("--samplers", default=",".join(SAMPLERS), help="default: %(default)s")
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
    if args.out:
        write_results(args.out, __doc__, time.perf_counter() - start, head=bench.git_commit(), cases=cases)


if __name__ == "__main__":
    main()
