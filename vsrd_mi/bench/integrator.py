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
from pathlib import Path
from typing import Callable

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import drjit as dr
import mitsuba as mi

from ..optimise.losses import to_float
from .measure import (KernelCounts, TimedIntegrator, cosine, label_error, labels_and_gradient, reference_chunks,
                      reference_fd_gradient, reference_samples)
from .scenes import QUICK, BenchConfig, CaseData, case_data, case_seed, load_integrator

SAMPLINGS = ("dense", "adaptive")
#: Environment variable marking the child process started by ``--fresh-cache``.
FRESH_CACHE_CHILD = "VSRD_MI_BENCH_FRESH_CACHE_CHILD"
#: Dr.Jit's kernel cache directory variable (default ``~/.drjit``).
DRJIT_CACHE_ENV = "DRJIT_CACHE_DIR"
#: The speed target of the task: adaptive at least this much faster than dense at 6 / 16k.
TARGET_SPEEDUP = 10.0
TARGET_CASE = (6, 16384)


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
