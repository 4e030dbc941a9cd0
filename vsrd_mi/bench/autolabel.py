"""Run time versus error of the autolabeling: ``vsrd-mi bench autolabel [--json PATH] [--quick]``.

Synthetic KITTI-360 sequences with known boxes (a static-heavy and a dynamic-heavy one, fixed
seeds; generated once and cached under ``--data-dir``) are autolabelled with a grid of settings
(sampling, rays per step, band samples K, step budget / early stop, residual, velocity,
initialisation). Every setting runs in its own process (so its peak resident memory is its own)
on the same target frames, and is scored with the evaluator (:mod:`vsrd_mi.evaluate`) on those
target frames: mean 3D / BEV IoU of Hungarian-matched pairs (static / dynamic) and AP|R40.

Outputs (``--out``, default ``benchmarks/``): ``autolabel.json`` (everything), ``autolabel.csv``
(one row per dataset x setting), ``autolabel_pareto.png`` (seconds per target vs 1 - recall-weighted
mean 3D IoU, i.e. missed ground truth counts as IoU 0)
and ``autolabel_ablation.md`` (the paper's ablation order on the dynamic-heavy set:
projection only -> + silhouette -> + residual -> + velocity -> + initialisation, then the default).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..optimise.config import (LONG_SCHEDULE_SHAPE_PRIOR, SHAPE_PRIOR_FIELDS, AutolabelConfig, default_config,
                               paper_config)


@dataclass(frozen=True)
class BenchDataset:
    """A synthetic sequence of the benchmark (see :func:`vsrd_mi.synth.generate_sequence`)."""

    name: str
    n_static: int
    n_dynamic: int
    seed: int
    frames: int = 30
    #: Target frames scored per dataset (the middle ones of the selection; 0 = all).
    max_targets: int = 0


@dataclass(frozen=True)
class BenchSetting:
    """One configuration: overrides of :func:`default_config` (nested dicts merge)."""

    name: str
    overrides: dict = field(default_factory=dict)
    #: Start from the ``paper`` preset instead of the default.
    paper: bool = False


DATASETS = (BenchDataset("static-heavy", n_static=5, n_dynamic=1, seed=1101),
            BenchDataset("dynamic-heavy", n_static=2, n_dynamic=4, seed=2202))

NO_SIL = {"weights": {"silhouette": 0.0}}
#: The paper's ablation order (Table "multi-view 3D autolabeling"), each row adding one component,
#: then the default (which leaves the residual field off, see ``AutolabelConfig.residual``).
ABLATION = (
    BenchSetting("abl-projection", {**NO_SIL, "residual": False, "velocity": False, "init": False}),
    BenchSetting("abl-+silhouette", {"residual": False, "velocity": False, "init": False}),
    BenchSetting("abl-+residual", {"residual": True, "velocity": False, "init": False}),
    BenchSetting("abl-+velocity", {"residual": True, "init": False}),
    BenchSetting("abl-+init", {"residual": True}),
    BenchSetting("default", {}),
)

GRID = (
    BenchSetting("dense", {"sampling": "dense"}),
    BenchSetting("rays-500", {"rays_per_step": 500}),
    BenchSetting("rays-2000", {"rays_per_step": 2000}),
    BenchSetting("K-8", {"band_samples": 8}),
    BenchSetting("K-32", {"band_samples": 32}),
    BenchSetting("no-isolated", {"isolated_rays": False}),
    BenchSetting("steps-300", {"steps": 300, "warmup_steps": 100}),
    BenchSetting("steps-1200", {"steps": 1200, "warmup_steps": 400}),
    BenchSetting("no-early-stop", {"early_stop": {"enabled": False}}),
    BenchSetting("residual", {"residual": True}),
    BenchSetting("no-velocity", {"velocity": False}),
    BenchSetting("no-init", {"init": False}),
    BenchSetting("init-weight-1", {"weights": {"init": 1.0}}),
    BenchSetting("init-dynamic-paper", {"weights": {"init_dynamic": 0.1}}),
    BenchSetting("init-paper", {"weights": {"init": 0.1, "init_dynamic": 0.1}}),
    BenchSetting("init-static-20", {"weights": {"init": 20.0}}),
    #: the size / yaw prior of the ``paper`` preset on the default (off there since it measured worse)
    BenchSetting("shape-prior", {"weights": {k: LONG_SCHEDULE_SHAPE_PRIOR for k in SHAPE_PRIOR_FIELDS}}),
    BenchSetting("containment", {"weights": {"projection_mode": "containment"}}),
    #: the paper's projection of the 8 box corners instead of the car profile (``CarProfile``)
    BenchSetting("box-corners", {"car_profile": {"clearance": 0.0, "overhang": 0.0, "corner": 0.0}}),
    #: the car profile without its cut plan corners (``CarProfile.corner``)
    BenchSetting("square-corners", {"car_profile": {"corner": 0.0}}),
    #: every target's own boxes in the labels (no sequence-level consensus of parked cars)
    BenchSetting("no-consensus", {"consensus": {"enabled": False}}),
    BenchSetting("paper", {}, paper=True),
    #: the paper's schedule, losses and residual field with the adaptive sampler: separates the
    #: sampler's share of the paper-vs-default difference from the schedule's
    BenchSetting("paper-adaptive", {"sampling": "adaptive"}, paper=True),
    #: ... and without the residual field (3000 box-only steps): separates the field's share
    BenchSetting("paper-box-only", {"sampling": "adaptive", "residual": False}, paper=True),
)

#: --quick: the default and the switches the issues ask to be measured (one target per dataset).
QUICK_SETTINGS = ("default", "residual", "no-velocity", "no-init", "abl-projection")
#: Step budget of --quick runs (the schedules are compressed accordingly).
QUICK_STEPS = 150


def merge(base: dict, over: dict) -> dict:
    """``base`` with ``over`` merged in (nested dicts merge key by key)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def setting_config(setting: BenchSetting, steps: int | None = None) -> AutolabelConfig:
    """The full configuration of a setting (``steps`` scales the step budget and warm-up)."""
    base = (paper_config() if setting.paper else default_config()).to_dict()
    cfg = AutolabelConfig.from_dict(merge(base, setting.overrides))
    if steps is not None and steps < cfg.steps:
        cfg = cfg.replace(warmup_steps=max(1, round(cfg.warmup_steps * steps / cfg.steps)), steps=steps)
    return cfg


def ensure_dataset(data_dir: Path, ds: BenchDataset) -> Path:
    """Root of the dataset's sequence (generated unless a finished copy is cached)."""
    from ..synth import generate_sequence

    root = data_dir / f"{ds.name}-s{ds.seed}-f{ds.frames}"
    done = root / "DONE"
    if not done.is_file():
        if root.exists():
            shutil.rmtree(root)
        t = time.perf_counter()
        generate_sequence(root, seq=0, frames=ds.frames, n_static=ds.n_static, n_dynamic=ds.n_dynamic,
                          seed=ds.seed)
        done.write_text(f"{time.perf_counter() - t:.1f} s\n")
    return root


def bench_targets(root: Path, ds: BenchDataset) -> list[int]:
    """Target frames scored on a dataset: the selection's, thinned to ``max_targets`` middle ones."""
    from ..data.kitti360 import Sequence
    from ..data.selection import select_targets

    targets = [s.target for s in select_targets(Sequence(root, 0))]
    if ds.max_targets and len(targets) > ds.max_targets:
        mid = len(targets) // 2
        lo = max(0, mid - ds.max_targets // 2)
        targets = targets[lo:lo + ds.max_targets]
    return targets


def _worker(root: str, targets: list[int], cfg: dict, out_dir: str, result_path: str) -> None:
    """Child process: autolabel ``targets`` with ``cfg`` and write timings + peak memory."""
    import vsrd_mi  # noqa: F401  (variant and plugins)
    from ..batch.tasks import TargetTask
    from ..data.kitti360 import Sequence
    from ..autolabel.job import process_target

    seq = Sequence(root, 0)
    rows = []
    for frame in targets:
        task = TargetTask(root=root, sequence=seq.name, frame=frame, output_dir=out_dir, config=cfg)
        t = time.perf_counter()
        try:
            res = process_target(task)
            rows.append({"frame": frame, "status": res.status, "seconds": time.perf_counter() - t,
                         "error": res.error})
        except Exception as exc:  # recorded, the setting goes on with its other targets
            rows.append({"frame": frame, "status": "failed", "seconds": time.perf_counter() - t,
                         "error": f"{type(exc).__name__}: {exc}"})
    # the sequence-level step `vsrd-mi autolabel` runs after its targets (labels of parked cars)
    from ..optimise.config import AutolabelConfig
    from ..autolabel.consensus import apply_consensus

    t = time.perf_counter()
    try:
        full = AutolabelConfig.from_dict(cfg)
        apply_consensus(Path(out_dir) / seq.name, seq, full.consensus, full.heading)
        consensus_error = None
    except Exception as exc:  # recorded; the targets' own labels are scored
        consensus_error = f"{type(exc).__name__}: {exc}"
    consensus_seconds = time.perf_counter() - t
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    Path(result_path).write_text(json.dumps({"targets": rows, "peak_rss_mib": peak_kib / 1024.0,
                                             "consensus_seconds": consensus_seconds,
                                             "consensus_error": consensus_error}))


def run_setting(root: Path, targets: list[int], cfg: AutolabelConfig, work: Path) -> dict:
    """Autolabel in a fresh process and evaluate the target frames."""
    from ..evaluate.sequence import evaluate_sequence

    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    result_path = work / "run.json"
    job = json.dumps({"root": str(root), "targets": targets, "cfg": cfg.to_dict(),
                      "out_dir": str(work / "out"), "result_path": str(result_path)})
    wall = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", "import sys, json; from vsrd_mi.bench.autolabel import _worker; "
                           "_worker(**json.loads(sys.argv[1]))", job])
    wall = time.perf_counter() - wall
    if proc.returncode != 0 or not result_path.is_file():
        return {"error": f"worker exited with {proc.returncode}", "wall_seconds": wall}
    run = json.loads(result_path.read_text())
    ok = [r for r in run["targets"] if r["status"] == "done"]
    ev = evaluate_sequence(work / "out", root, 0, frames=targets)
    pairs = ev["pairs"]
    ap3d = ev["ap"]["3d"]
    apbev = ev["ap"]["bev"]
    return {
        "wall_seconds": wall,
        "seconds_per_target": (sum(r["seconds"] for r in ok) / len(ok)) if ok else None,
        "peak_rss_mib": run["peak_rss_mib"],
        "consensus_seconds": run.get("consensus_seconds"),
        "consensus_error": run.get("consensus_error"),
        "failed": [r for r in run["targets"] if r["status"] != "done"],
        "mean_iou_3d": pairs["all"]["mean_iou_3d"],
        "mean_iou_3d_static": pairs["static"]["mean_iou_3d"],
        "mean_iou_3d_dynamic": pairs["dynamic"]["mean_iou_3d"],
        "mean_iou_bev": pairs["all"]["mean_iou_bev"],
        "recall_weighted_iou_3d": pairs["all"]["recall_weighted_iou_3d"],
        "centre_error_m": pairs["all"]["centre_error_m"],
        "ap3d_0.5_r40": ap3d[_key(ap3d, 0.5)]["easy"]["R40"] if "easy" in ap3d[_key(ap3d, 0.5)] else None,
        "apbev_0.5_r40": apbev[_key(apbev, 0.5)]["easy"]["R40"] if "easy" in apbev[_key(apbev, 0.5)] else None,
        "apbev_0.3_r40": apbev[_key(apbev, 0.3)]["easy"]["R40"] if "easy" in apbev[_key(apbev, 0.3)] else None,
    }


def _key(table: dict, threshold: float) -> str:
    """The threshold key of an AP table (``"0.5"``-like formatting of the evaluator)."""
    for k in table:
        if abs(float(k) - threshold) < 1e-9:
            return k
    raise KeyError(threshold)


def write_outputs(results: list[dict], out_dir: Path, meta: dict) -> None:
    """JSON, CSV, Pareto plot and the ablation table."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "autolabel.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    cols = ["dataset", "setting", "seconds_per_target", "peak_rss_mib", "mean_iou_3d", "mean_iou_3d_static",
            "mean_iou_3d_dynamic", "mean_iou_bev", "recall_weighted_iou_3d", "centre_error_m", "ap3d_0.5_r40", "apbev_0.5_r40",
            "apbev_0.3_r40"]
    with open(out_dir / "autolabel.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in results:
            w.writerow(r)
    _plot(results, out_dir / "autolabel_pareto.png")
    _ablation_table(results, out_dir / "autolabel_ablation.md")


def _plot(results: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for ds, marker in zip(sorted({r["dataset"] for r in results}), "os^"):
        pts = [r for r in results if r["dataset"] == ds and r.get("recall_weighted_iou_3d") is not None
               and r.get("seconds_per_target")]
        ax.scatter([r["seconds_per_target"] for r in pts], [1.0 - r["recall_weighted_iou_3d"] for r in pts],
                   marker=marker, label=ds)
        for r in pts:
            ax.annotate(r["setting"], (r["seconds_per_target"], 1.0 - r["recall_weighted_iou_3d"]), fontsize=7,
                        rotation=20)
    ax.set_xscale("log")
    ax.set_xlabel("seconds per target frame (CPU, llvm_ad_rgb)")
    ax.set_ylabel("1 - mean 3D IoU (unmatched ground truth counts as 0)")
    ax.set_title("vsrd-mi autolabel: run time vs error")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def _ablation_table(results: list[dict], path: Path) -> None:
    rows = ["| setting | mean 3D IoU | static | dynamic | AP3D@0.5 R40 (easy) | APBEV@0.5 R40 (easy) | s/target |",
            "|---|---|---|---|---|---|---|"]
    names = [s.name for s in ABLATION]
    for name in names:
        for r in results:
            if r["dataset"] == "dynamic-heavy" and r["setting"] == name:
                rows.append(f"| {name} | {_fmt(r.get('mean_iou_3d'))} | {_fmt(r.get('mean_iou_3d_static'))} | "
                            f"{_fmt(r.get('mean_iou_3d_dynamic'))} | {_fmt(r.get('ap3d_0.5_r40'))} | "
                            f"{_fmt(r.get('apbev_0.5_r40'))} | {_fmt(r.get('seconds_per_target'))} |")
    path.write_text("Ablation on the dynamic-heavy synthetic sequence (paper order; each row adds one "
                    "component; `abl-+init` = every component of the paper; `default` = the fast default, "
                    "residual field off).\n\n" + "\n".join(rows) + "\n")


def run(args: argparse.Namespace) -> int:
    data_dir = Path(args.data_dir)
    work_dir = Path(args.work_dir)
    settings = {s.name: s for s in ABLATION + GRID}
    names = list(QUICK_SETTINGS) if args.quick else list(settings)
    if args.settings:
        names = args.settings
    steps = args.steps or (QUICK_STEPS if args.quick else None)
    datasets = [BenchDataset(d.name, d.n_static, d.n_dynamic, d.seed, d.frames,
                             max_targets=args.max_targets or (1 if args.quick else 0)) for d in DATASETS]
    results = []
    start = time.perf_counter()
    for ds in datasets:
        root = ensure_dataset(data_dir, ds)
        targets = bench_targets(root, ds)
        for name in names:
            cfg = setting_config(settings[name], steps)
            print(f"[{ds.name}] {name}: targets {targets} ...", flush=True)
            r = run_setting(root, targets, cfg, work_dir / ds.name / name)
            r.update(dataset=ds.name, setting=name, targets=targets, config=cfg.to_dict())
            results.append(r)
            print(f"    {_fmt(r.get('seconds_per_target'))} s/target, mean 3D IoU {_fmt(r.get('mean_iou_3d'))} "
                  f"(static {_fmt(r.get('mean_iou_3d_static'))}, dynamic {_fmt(r.get('mean_iou_3d_dynamic'))}), "
                  f"peak {_fmt(r.get('peak_rss_mib'))} MiB", flush=True)
            write_outputs(results, Path(args.out), _meta(args, datasets, steps, start))
    if args.json:
        Path(args.json).write_text(json.dumps({"meta": _meta(args, datasets, steps, start), "results": results},
                                              indent=1))
    return 0


def _meta(args, datasets, steps, start) -> dict:
    import platform
    return {"quick": bool(args.quick), "steps_override": steps, "datasets": [asdict(d) for d in datasets],
            "elapsed_seconds": time.perf_counter() - start, "python": sys.version.split()[0],
            "machine": platform.machine(), "cpus": os.cpu_count(),
            "command": "vsrd-mi bench autolabel" + (" --quick" if args.quick else "")}


def register(bench_subparsers) -> None:
    """Add ``autolabel`` to the ``vsrd-mi bench`` sub-commands."""
    p = bench_subparsers.add_parser("autolabel", help="run time vs error of the autolabeling on synthetic sequences")
    p.add_argument("--quick", action="store_true",
                   help=f"one target per dataset, {len(QUICK_SETTINGS)} settings, {QUICK_STEPS} steps")
    p.add_argument("--json", help="also write the results to this path")
    p.add_argument("--out", default="benchmarks", help="directory of autolabel.{json,csv}, plot and ablation table")
    p.add_argument("--data-dir", default="runs/bench-data", help="cache of the generated sequences")
    p.add_argument("--work-dir", default="runs/bench-autolabel", help="per-setting outputs")
    p.add_argument("--settings", nargs="+", help="run only these settings")
    p.add_argument("--steps", type=int, help="cap the step budget of every setting")
    p.add_argument("--max-targets", type=int, default=0, help="target frames per dataset (0 = all)")
    p.set_defaults(func=run)
