"""Memory over many targets in one process: ``vsrd-mi bench memory`` (batches must not grow without bound).

Runs :func:`vsrd_mi.autolabel.job.process_target` repeatedly in one process on the target
frames of a sequence (cycling through them, each run into a fresh output directory so nothing is
skipped) and records the resident set size after every target. Kept AD graphs, cached kernels
per target or leaked Dr.Jit arrays show up as a steady climb; a bounded process levels off after
the first targets (kernel compilation, allocator pools).

Usage::

    vsrd-mi bench memory --runs 120 --steps 60 --residual --json benchmarks/memory.json

writes the JSON and a PNG of RSS per run beside it.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from ..autolabel.job import process_target  # noqa: E402
from ..batch.tasks import TargetTask  # noqa: E402
from ..data.kitti360 import Sequence  # noqa: E402
from ..data.selection import select_targets  # noqa: E402
from ..optimise.config import default_config  # noqa: E402


def rss_mib() -> float:
    """Current resident set size of this process (MiB), from /proc."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS in /proc/self/status")


def plot(rows: list[dict], summary: dict, path: Path) -> None:
    """RSS after every target (PNG)."""
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot([r["run"] for r in rows], [r["rss_mib"] for r in rows], marker=".")
    ax.set_xlabel("target run in one process")
    ax.set_ylabel("resident set size (MiB)")
    ax.set_title(f"memory over {summary['runs']} targets ({summary['steps']} steps each, "
                 f"residual {'on' if summary['residual'] else 'off'})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def register(subparsers: argparse._SubParsersAction) -> None:
    ap = subparsers.add_parser("memory", help="resident memory after every target in one process",
                               description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="scenes/kitti360-synth")
    ap.add_argument("--sequence", type=int, default=0)
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--json", default="benchmarks/memory.json")
    ap.add_argument("--residual", action="store_true",
                    help="with the residual field (the default preset has none; it holds the largest AD graphs)")
    ap.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    seq = Sequence(args.root, args.sequence)
    targets = [s.target for s in select_targets(seq)]
    cfg = default_config().replace(steps=args.steps, warmup_steps=args.steps // 3,
                                   residual=args.residual).to_dict()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            frame = targets[i % len(targets)]
            task = TargetTask(root=str(Path(args.root).resolve()), sequence=seq.name, frame=frame,
                              output_dir=str(Path(tmp) / f"run{i:04d}"), config=cfg)
            t = time.perf_counter()
            status = process_target(task).status
            rows.append({"run": i, "frame": frame, "status": status, "seconds": time.perf_counter() - t,
                         "rss_mib": rss_mib()})
            print(f"run {i:3d} frame {frame:4d} {status} {rows[-1]['seconds']:.1f} s  RSS {rows[-1]['rss_mib']:.0f} MiB",
                  flush=True)
    n = len(rows)
    first, second = rows[: n // 2], rows[n // 2:]
    summary = {
        "runs": n, "steps": args.steps, "residual": args.residual, "targets": targets,
        "rss_after_first_cycle_mib": rows[min(len(targets), n) - 1]["rss_mib"],
        "rss_final_mib": rows[-1]["rss_mib"],
        "mean_rss_first_half_mib": sum(r["rss_mib"] for r in first) / max(len(first), 1),
        "mean_rss_second_half_mib": sum(r["rss_mib"] for r in second) / max(len(second), 1),
    }
    summary["growth_per_run_second_half_mib"] = (
        (second[-1]["rss_mib"] - second[0]["rss_mib"]) / max(len(second) - 1, 1) if len(second) > 1 else None)
    Path(args.json).write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))
    plot(rows, summary, Path(args.json).with_suffix(".png"))
    print(json.dumps(summary, indent=1))
    return 0

