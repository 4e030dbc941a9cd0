"""Per-target speed and accuracy of the autolabeling, side by side with another git revision:
``vsrd-mi bench autolabel [--rev REV] [--cold] [--sequence [DATA]]``.

Every measurement runs in a fresh process (:mod:`vsrd_mi.bench.autolabel_worker`) with
``PYTHONPATH`` pointing at the code being measured: this checkout, and with ``--rev`` an export of
that git revision (``git archive``), so both sides run on the same machine, targets and
configuration (each revision builds the preset with its own defaults, plus the same ``--set``
overrides). The runs are:

1. a warm-up round, one process per side over every target: fills the kernel cache and records
   Dr.Jit's kernel history (kernels launched per step, new kernels in a target's first steps and
   after them); its times are not used;
2. ``--rounds`` timed rounds without the kernel history, the sides alternating (the order flips
   every round), each a process over every target: per-target wall time and its phases, steps,
   peak resident memory; the mean over rounds per target is reported, and the ratio of the two
   sides per target and over all targets;
3. with ``--cold``, the first target once per side with an empty kernel cache (``DRJIT_CACHE_DIR``
   set to a new directory);
4. with ``--sequence DATA`` (default ``suite:validation:long``, 200 frames), that sequence labelled
   end to end by ``vsrd-mi autolabel`` per side: wall time and labelled frames per hour.

The labels of the last timed round are evaluated with this checkout's evaluator
(:mod:`vsrd_mi.evaluate`): mean 3D IoU of parked and moving cars, heading accuracy, angled cars'
yaw error, size bias, the share of cars without a box, AP and AOS. Two rounds of one side giving
different label files are reported (``deterministic``).

Data (``--data``): ``suite:SET[:PRESET,...][@ROOT]`` (the sequences of a synthetic set of
:mod:`vsrd_mi.synth.suites`: read from ``ROOT`` as they are there, or written under
``--data-dir/SET`` unless there with the same fingerprint),
``bundled`` (``scenes/kitti360-synth``) and ``synth:STATIC,DYNAMIC,SEED[,FRAMES]`` (one
:func:`vsrd_mi.synth.generate_sequence` sequence, cached under ``--data-dir``). Every labelled
frame is evaluated, pooled over the sequences, with the figures of ``vsrd-mi bench validation``.
Results: ``benchmarks/autolabel.json`` (``--out``) and, with ``--sequence``,
``benchmarks/autolabel_sequence.json``.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..data.kitti360 import Sequence, sequence_name
from ..data.selection import select_targets
from ..evaluate.sequence import EvalConfig, evaluate_frames, sequence_frames
from ..synth import generate_sequence
from ..errors import DataError
from ..synth.suites import MANIFEST, read_manifest, select, suite, write_suite
from . import autolabel_worker
from .validation import headline

#: Root of this checkout (the code measured as ``this``).
REPO_ROOT = Path(__file__).resolve().parents[2]
#: The bundled sequence (``--data bundled``).
BUNDLED_ROOT = REPO_ROOT / "scenes" / "kitti360-synth"
#: Data of a default run: the validation set (its first round: six sequences, see SUITE_ROUNDS).
DEFAULT_DATA = ("suite:validation",)
#: Rounds of a ``suite:`` set timed: the first (one street per preset); the later rounds of the
#: validation set are there for its accuracy figures' sampling spread, not for timings.
SUITE_ROUNDS = 1
#: The whole-sequence figure's sequence: the validation set's 200-frame street.
DEFAULT_SEQUENCE = "suite:validation:long"
#: Frames of a ``synth:`` sequence when its spec does not say.
DEFAULT_SYNTH_FRAMES = 30
#: Name of the side measuring this checkout.
THIS = "this"


@dataclass(frozen=True)
class BenchSequence:
    """One sequence of the benchmark and the target frames run on it."""

    name: str
    root: str
    sequence: str
    targets: tuple[int, ...]


@dataclass(frozen=True)
class Side:
    """Code measured: a name and the source tree put on ``PYTHONPATH``."""

    name: str
    tree: Path

    def environment(self, cache_dir: str | None = None) -> dict:
        """The worker's environment: the tree (and its plugin folder) first on the path."""
        env = dict(os.environ)
        paths = [str(self.tree), str(self.tree / "plugins")]
        if (self.tree / "plugins" / "__init__.py").is_file():
            # older trees map the folder plugins/ itself to the package vsrd_plugins (package-dir)
            shim = self.tree / ".bench-path"
            shim.mkdir(exist_ok=True)
            if not (shim / "vsrd_plugins").exists():
                (shim / "vsrd_plugins").symlink_to(self.tree / "plugins", target_is_directory=True)
            paths.append(str(shim))
        env["PYTHONPATH"] = os.pathsep.join(paths + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        if cache_dir is not None:
            env["DRJIT_CACHE_DIR"] = cache_dir
        return env


def export_revision(rev: str, dest: Path) -> Path:
    """The tree of git revision ``rev`` of this repository, written to ``dest`` (``git archive``)."""
    dest.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(REPO_ROOT), "archive", "--format=tar", rev],
                             capture_output=True, check=False)
    if archive.returncode != 0:
        raise ValueError(f"git revision {rev!r}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest


def data_sequences(spec: str, data_dir: Path) -> list[tuple[str, Path, int]]:
    """``(name, absolute root, sequence number)`` of each sequence of a ``--data`` item (a
    ``suite:`` set or a ``synth:`` sequence is generated unless a finished copy is there); the
    workers run elsewhere, so roots are absolute."""
    data_dir = data_dir.resolve()
    if spec == "bundled":
        return [(spec, BUNDLED_ROOT, 0)]
    kind, _, args = spec.partition(":")
    if kind == "suite":
        args, _, where = args.partition("@")
        set_name, _, presets = args.partition(":")
        if set_name not in ("validation", "development"):
            raise ValueError(f"--data {spec!r}: expected 'suite:validation' or 'suite:development'[:PRESET,...][@ROOT]")
        members = [m for preset in (presets.split(",") if presets else [None])
                   for m in select(suite(set_name), preset, SUITE_ROUNDS)]
        if where:  # a set written elsewhere is only read: its sequences must be there
            root = Path(where).resolve()
            missing = [m.scenario.name for m in members
                       if sequence_name(m.sequence) not in read_manifest(root)["sequences"]]
            if missing:
                raise DataError(root / MANIFEST, f"no sequence of the preset(s) {missing} (the benchmark does "
                                                 "not write into a given root)")
        else:
            root = data_dir / set_name
            for preset in presets.split(",") if presets else [None]:
                write_suite(root, set_name, only=preset, rounds=SUITE_ROUNDS)
        return [(f"{set_name}/{m.scenario.name}" + (f"-r{m.round}" if m.round else ""), root, m.sequence)
                for m in members]
    values = args.split(",")
    if kind != "synth" or len(values) not in (3, 4) or not all(v.strip().isdigit() for v in values):
        raise ValueError(f"--data {spec!r}: expected 'suite:SET[:PRESET,...][@ROOT]', 'bundled' or "
                         "'synth:STATIC,DYNAMIC,SEED[,FRAMES]'")
    n_static, n_dynamic, seed, frames = (list(map(int, values)) + [DEFAULT_SYNTH_FRAMES])[:4]
    root = data_dir / f"synth-s{n_static}-d{n_dynamic}-seed{seed}-f{frames}"
    if not (root / "DONE").is_file():
        if root.exists():
            shutil.rmtree(root)
        start = time.perf_counter()
        generate_sequence(root, seq=0, frames=frames, n_static=n_static, n_dynamic=n_dynamic, seed=seed)
        (root / "DONE").write_text(f"{time.perf_counter() - start:.1f} s\n")
    return [(spec, root, 0)]


def middle(values: list[int], count: int) -> list[int]:
    """At most ``count`` of ``values`` around their middle (all of them for ``count <= 0``)."""
    if count <= 0 or len(values) <= count:
        return list(values)
    lo = max(0, len(values) // 2 - count // 2)
    return values[lo:lo + count]


def bench_sequences(data: list[str], data_dir: Path, max_targets: int) -> list[BenchSequence]:
    """The benchmark's sequences with their target frames (the selection's, thinned to the middle)."""
    out = []
    for spec in data:
        for name, root, number in data_sequences(spec, data_dir):
            targets = middle([s.target for s in select_targets(Sequence(root, number))], max_targets)
            out.append(BenchSequence(name, str(root), sequence_name(number), tuple(targets)))
    return out


def run_worker(side: Side, job: dict, work: Path, cache_dir: str | None = None) -> dict:
    """Run :mod:`.autolabel_worker` on ``job`` for ``side`` in a fresh process; its result."""
    work.mkdir(parents=True, exist_ok=True)
    job_path, result_path = work / "job.json", work / "result.json"
    job_path.write_text(json.dumps(job, indent=1))
    result_path.unlink(missing_ok=True)
    proc = subprocess.run([sys.executable, "-P", autolabel_worker.__file__, str(job_path), str(result_path)],
                          env=side.environment(cache_dir), cwd=str(work))
    if proc.returncode != 0 or not result_path.is_file():
        raise RuntimeError(f"{side.name}: worker exited with {proc.returncode} (job {job_path})")
    return json.loads(result_path.read_text())


def target_job(sequences: list[BenchSequence], out: Path, args: argparse.Namespace, kernel_history: bool,
               first_only: bool = False) -> dict:
    """The worker job of one run over the benchmark's targets (outputs under ``out``)."""
    items = []
    for k, s in enumerate(sequences):
        targets = list(s.targets[:1]) if first_only else list(s.targets)
        items.append({"name": s.name, "root": s.root, "sequence": s.sequence, "targets": targets,
                      "out_dir": str(out / f"data{k}")})
        if first_only:
            break
    return {"preset": args.config, "overrides": list(args.set or []), "seed": args.seed,
            "kernel_history": kernel_history, "sequences": items}


def labels_identical(a: Path, b: Path) -> list[str]:
    """Label files (relative paths) that differ between two output trees or exist in one only."""
    files_a = {p.relative_to(a) for p in a.rglob("labels/*.txt")}
    files_b = {p.relative_to(b) for p in b.rglob("labels/*.txt")}
    differ = sorted(str(p) for p in files_a ^ files_b)
    differ += sorted(str(p) for p in files_a & files_b if not filecmp.cmp(a / p, b / p, shallow=False))
    return differ


def evaluation(sequences: list[BenchSequence], out: Path) -> dict:
    """This checkout's evaluation of one run's labels: every labelled frame, per sequence and
    pooled over the sequences, with ``vsrd-mi bench validation``'s headline figures."""
    config = EvalConfig()
    frames, per = [], {}
    for k, s in enumerate(sequences):
        seq_frames, _ = sequence_frames(out / f"data{k}", s.root, s.sequence, None, config)
        frames += seq_frames
        per[s.name] = headline(evaluate_frames(seq_frames, config))
    pooled = evaluate_frames(frames, config)
    return {"figures": headline(pooled), "pairs": pooled["pairs"], "ap": pooled["ap"],
            "labelled_frames": len(frames), "sequences": per}


def per_target_rows(runs: list[dict]) -> list[dict]:
    """One row per (sequence, target): times of every timed round, mean phases, steps, kernels."""
    rows = {}
    for run in runs:
        for s in run["sequences"]:
            for t in s["targets"]:
                row = rows.setdefault((s["name"], t["frame"]), {
                    "data": s["name"], "sequence": s["sequence"], "frame": t["frame"], "seconds": [], "phases": {},
                    "status": []})
                row["seconds"].append(t["seconds"])
                row["status"].append(t["status"])
                for k, v in t["phases"].items():
                    row["phases"].setdefault(k, []).append(v)
                row["steps"] = t.get("steps")
    out = []
    for row in rows.values():
        row["mean_seconds"] = float(np.mean(row["seconds"]))
        row["phases"] = {k: float(np.mean(v)) for k, v in row["phases"].items()}
        row["steps_per_second"] = (row["steps"] / row["phases"]["optimisation"]
                                   if row.get("steps") and row["phases"].get("optimisation") else None)
        out.append(row)
    return out


def kernel_summary(run: dict) -> dict:
    """Kernel figures of the warm-up (kernel history) run, over all its targets."""
    ks = [t["kernels"] for s in run["sequences"] for t in s["targets"] if t.get("kernels")]
    launched = [k["launched_per_step"] for k in ks if k["launched_per_step"] is not None]
    return {
        "launched_per_step": float(np.mean(launched)) if launched else None,
        "new_after_warmup": sum(k["new_after_warmup"] for k in ks),
        "compiled_after_warmup": sum(k["compiled_after_warmup"] for k in ks),
        "new_in_warmup_per_target": float(np.mean([k["new_in_warmup"] for k in ks])) if ks else None,
        "warmup_steps": autolabel_worker.WARMUP_STEPS,
        "per_target": ks,
    }


def side_summary(rows: list[dict], runs: list[dict], warm: dict, ev: dict) -> dict:
    """Headline figures of one side."""
    done = [r for r in rows if all(s == "done" for s in r["status"])]
    steps = [r["steps"] for r in done if r.get("steps")]
    optimise = [r["phases"].get("optimisation", 0.0) for r in done if r.get("steps")]
    phases = {k: float(np.mean([r["phases"].get(k, 0.0) for r in done])) for k in (done[0]["phases"] if done else {})}
    return {
        "targets": len(rows), "failed": [r for r in rows if r not in done],
        "seconds_per_target": float(np.mean([r["mean_seconds"] for r in done])) if done else None,
        "phases_per_target": phases,
        "steps_per_target": float(np.mean(steps)) if steps else None,
        "steps_per_second": float(sum(steps) / sum(optimise)) if steps and sum(optimise) > 0 else None,
        "peak_rss_mib": max(run["peak_rss_mib"] for run in runs),
        "kernels": kernel_summary(warm),
        "mean_iou_3d_parked": ev["figures"]["parked_iou"],
        "mean_iou_3d_moving": ev["figures"]["moving_iou"],
        "mean_iou_3d_all": ev["pairs"]["all"]["mean_iou_3d"],
        "figures": ev["figures"],
    }


def comparison(rows: dict[str, list[dict]], summaries: dict[str, dict], base: str) -> dict:
    """``base`` against this checkout: time ratios per target and over all, IoU differences."""
    mine = {(r["data"], r["frame"]): r["mean_seconds"] for r in rows[THIS]}
    theirs = {(r["data"], r["frame"]): r["mean_seconds"] for r in rows[base]}
    common = sorted(set(mine) & set(theirs))
    ratios = [theirs[k] / mine[k] for k in common]
    a, b = summaries[THIS], summaries[base]

    def diff(key: str) -> float | None:
        return None if a.get(key) is None or b.get(key) is None else a[key] - b[key]
    return {
        "speedup_total": sum(theirs[k] for k in common) / sum(mine[k] for k in common) if common else None,
        "speedup_per_target": {f"{s} {f}": r for (s, f), r in zip(common, ratios)},
        "speedup_geometric_mean": float(np.exp(np.mean(np.log(ratios)))) if ratios else None,
        "iou_3d_parked_difference": diff("mean_iou_3d_parked"),
        "iou_3d_moving_difference": diff("mean_iou_3d_moving"),
        "peak_rss_ratio": a["peak_rss_mib"] / b["peak_rss_mib"],
    }


def sequence_figure(sides: list[Side], spec: str, args: argparse.Namespace, work: Path) -> dict:
    """Label the sequence of ``spec`` end to end with ``vsrd-mi autolabel`` per side."""
    ((name, root, number),) = data_sequences(spec, Path(args.data_dir).resolve())
    seq = Sequence(root, number)
    out = {"data": spec, "root": str(root), "sequence": seq.name, "frames": len(seq.frames),
           "targets": len(select_targets(seq)), "sides": {}}
    for side in sides:
        dest = work / "sequence" / side.name
        if dest.exists():
            shutil.rmtree(dest)
        cli = ["autolabel", str(root), "--sequence", seq.name, "--out", str(dest), "--config", args.config]
        cli += [a for kv in (args.set or []) for a in ("--set", kv)]
        print(f"[sequence] {side.name}: vsrd-mi {' '.join(cli)}", flush=True)
        result = run_worker(side, {"cli": cli}, dest.parent / f"{side.name}-job")
        frames, _ = sequence_frames(dest, root, seq.name, None, EvalConfig())
        out["sides"][side.name] = {**result, "labelled_frames": len(frames),
                                   "labelled_frames_per_hour": 3600.0 * len(frames) / result["seconds"],
                                   "figures": headline(evaluate_frames(frames, EvalConfig()))}
    return out


def run(args: argparse.Namespace) -> int:
    work = Path(args.work_dir).resolve()
    data_dir = Path(args.data_dir).resolve()
    sequences = bench_sequences(args.data, data_dir, args.max_targets)
    for s in sequences:
        print(f"{s.name}: {s.root} targets {list(s.targets)}", flush=True)
    with tempfile.TemporaryDirectory(prefix="vsrd-bench-") as tmp:
        sides = [Side(THIS, REPO_ROOT)]
        if args.rev:
            sides.append(Side(args.rev, export_revision(args.rev, Path(tmp) / "rev")))
        start = time.perf_counter()
        warm = {}
        for side in sides:
            print(f"[warm-up, kernel history] {side.name}", flush=True)
            warm[side.name] = run_worker(side, target_job(sequences, work / side.name / "warmup", args, True),
                                         work / side.name / "warmup")
        cold = {}
        if args.cold:
            for side in sides:
                print(f"[cold kernel cache] {side.name}", flush=True)
                cache = tempfile.mkdtemp(prefix="drjit-cold-", dir=tmp)
                res = run_worker(side, target_job(sequences, work / side.name / "cold", args, True, first_only=True),
                                 work / side.name / "cold", cache_dir=cache)
                first = res["sequences"][0]["targets"][0]
                cold[side.name] = {"frame": first["frame"], "sequence": res["sequences"][0]["sequence"],
                                   "seconds": first["seconds"], "phases": first["phases"],
                                   "kernels": first.get("kernels")}
        runs: dict[str, list[dict]] = {side.name: [] for side in sides}
        for r in range(args.rounds):
            for side in (sides if r % 2 == 0 else sides[::-1]):
                print(f"[round {r + 1}/{args.rounds}] {side.name}", flush=True)
                out = work / side.name / f"round{r}"
                if out.exists():
                    shutil.rmtree(out)
                runs[side.name].append(run_worker(side, target_job(sequences, out, args, False), out))
        rows, summaries, deterministic, evals = {}, {}, {}, {}
        for side in sides:
            rounds = [work / side.name / f"round{r}" for r in range(args.rounds)]
            evals[side.name] = evaluation(sequences, rounds[-1])
            rows[side.name] = per_target_rows(runs[side.name])
            summaries[side.name] = side_summary(rows[side.name], runs[side.name], warm[side.name], evals[side.name])
            summaries[side.name]["cold_first_target"] = cold.get(side.name)
            deterministic[side.name] = {"differing_label_files": sorted(
                {f for r in rounds[1:] for f in labels_identical(rounds[0], r)})}
        result = {
            "meta": _meta(args, sequences, time.perf_counter() - start),
            "summary": summaries,
            "comparison": comparison(rows, summaries, args.rev) if args.rev else None,
            "deterministic": deterministic, "targets": rows, "evaluation": evals,
        }
        out_dir = Path(args.out)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "autolabel.json").write_text(json.dumps(result, indent=1))
        print(report(result), flush=True)
        if args.sequence:
            seq_result = {"meta": _meta(args, sequences, 0.0), **sequence_figure(sides, args.sequence, args, work)}
            (out_dir / "autolabel_sequence.json").write_text(json.dumps(seq_result, indent=1))
            for name, s in seq_result["sides"].items():
                print(f"[sequence] {name}: {s['seconds']:.0f} s, {s['labelled_frames']} labelled frames, "
                      f"{s['labelled_frames_per_hour']:.0f} per hour, peak {s['peak_rss_mib']:.0f} MiB")
    return 0


def _fmt(value, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


def report(result: dict) -> str:
    """A short text table of the headline figures."""
    lines = ["side | s/target | steps/s | steps | launched/step | new kernels after warm-up | peak MiB | "
             "3D IoU parked | moving"]
    for name, s in result["summary"].items():
        k = s["kernels"]
        lines.append(f"{name} | {_fmt(s['seconds_per_target'], '.2f')} | {_fmt(s['steps_per_second'], '.1f')} | "
                     f"{_fmt(s['steps_per_target'], '.0f')} | {_fmt(k['launched_per_step'], '.0f')} | "
                     f"{k['new_after_warmup']} | {_fmt(s['peak_rss_mib'], '.0f')} | "
                     f"{_fmt(s['mean_iou_3d_parked'])} | {_fmt(s['mean_iou_3d_moving'])}")
    c = result.get("comparison")
    if c:
        lines.append(f"speed-up {_fmt(c['speedup_total'], '.2f')}x over all targets (geometric mean "
                     f"{_fmt(c['speedup_geometric_mean'], '.2f')}x); 3D IoU difference parked "
                     f"{_fmt(c['iou_3d_parked_difference'], '+.4f')}, moving {_fmt(c['iou_3d_moving_difference'], '+.4f')}")
    for name, d in result["deterministic"].items():
        lines.append(f"{name}: label files differing between rounds: {len(d['differing_label_files'])}")
    return "\n".join(lines)


def _meta(args: argparse.Namespace, sequences: list[BenchSequence], elapsed: float) -> dict:
    commit = subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(REPO_ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True)
    return {"command": "vsrd-mi " + " ".join(sys.argv[1:]), "commit": commit.stdout.strip(),
            "uncommitted_changes": bool(dirty.stdout.strip()), "rev": args.rev, "rounds": args.rounds,
            "config": args.config, "overrides": list(args.set or []), "sequences": [asdict(s) for s in sequences],
            "elapsed_seconds": elapsed, "python": sys.version.split()[0], "machine": platform.machine(),
            "cpus": os.cpu_count(), "load_average": os.getloadavg()}


def register(bench_subparsers) -> None:
    """Add ``autolabel`` to the ``vsrd-mi bench`` sub-commands."""
    p = bench_subparsers.add_parser(
        "autolabel", help="per-target speed and accuracy of the autolabeling, optionally against a git revision",
        description=__doc__.split("\n\n")[0])
    p.add_argument("--rev", help="git revision run side by side (e.g. ed219dd)")
    p.add_argument("--data", nargs="+", default=list(DEFAULT_DATA),
                   help="sequences: 'suite:validation|development[:PRESET,...][@ROOT]', 'bundled', "
                        "'synth:STATIC,DYNAMIC,SEED[,FRAMES]'")
    p.add_argument("--max-targets", type=int, default=2, help="target frames per sequence, the middle ones (0 = all)")
    p.add_argument("--rounds", type=int, default=2, help="timed rounds per side (alternating)")
    p.add_argument("--cold", action="store_true", help="also time the first target with an empty kernel cache")
    p.add_argument("--sequence", nargs="?", const=DEFAULT_SEQUENCE, metavar="DATA",
                   help=f"also label one sequence end to end with vsrd-mi autolabel (default {DEFAULT_SEQUENCE}: "
                        "200 frames)")
    p.add_argument("--config", default="default", help="preset of each side's own configuration")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override of both sides' configuration")
    p.add_argument("--seed", type=int, default=0, help="seed of every target")
    p.add_argument("--out", default="benchmarks", help="directory of autolabel.json (and autolabel_sequence.json)")
    p.add_argument("--data-dir", default="runs/bench-data", help="cache of generated sequences")
    p.add_argument("--work-dir", default="runs/bench-autolabel", help="outputs of every run")
    p.set_defaults(func=run)
