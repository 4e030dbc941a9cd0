"""How fast can the adaptive sampler be with the residual field? Its step time next to the dense sampler's, with parts of its residual search switched off, and their label errors.

The integrator issue's target is adaptive >= 10x dense at 6 boxes / 16k rays. Without the
residual field the adaptive sampler meets it (``vsrd-mi bench integrator``); with the field it
does not. This script asks whether any setting of the current design could: on the integrator
benchmark's 6-box residual scene (same seed, same rays, s = 10) it times, side by side in one
loop (this machine is noisy: compare the ratios), the dense sampler with the field and the
adaptive sampler

* as it ships (band, tail and moved samples; isolated rays with their bands' anchors and the
  extrema of ``B + R`` only; :data:`SETTINGS`),
* without that isolated-ray layout (``isolated_rays`` off: every ray the full layout),
* without tail samples (``residual_tail = 0``: the band's samples only, moved to the extrema of
  ``B + R`` they find),
* without any residual search (``residual_scan = 0``: the band sits at the box's own minimum, no
  tails, no moved samples, no chord grid or lattice),
* and, for scale, without the residual field at all (boxes only, same rays).

For every setting with the field it also reports the labels' error against the brute-force
reference (:func:`vsrd_mi.bench.integrator.reference_chunk`) on the first 512 rays and the
gradient cosine with it: the switched-off settings are floors, not candidates, unless they keep
the issue's bounds (max 0.01, cosine 0.99). The ratio dense / setting is the speed-up each
would give.

Usage::

    python benchmarks/residual_floor.py --out benchmarks/residual_floor.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from common import side_by_side_steps, write_results  # noqa: E402
import vsrd_mi  # noqa: F401,E402  (sets the variant, registers the plugins)
from vsrd_mi.bench import integrator as bench  # noqa: E402

#: (name, sampling, residual field on, integrator options): the runs compared.
SETTINGS = (
    ("dense", "dense", True, {}),
    ("adaptive (default)", "adaptive", True, {}),
    ("adaptive, no isolated-ray layout", "adaptive", True, {"isolated_rays": False}),
    ("adaptive, no tail samples", "adaptive", True, {"residual_tail": 0}),
    ("adaptive, no residual search", "adaptive", True, {"residual_tail": 0, "residual_scan": 0}),
    ("adaptive, no residual field", "adaptive", False, {}),
)
#: The issue's target speed-up and accuracy bounds.
TARGET_SPEEDUP = 10.0
MAX_LABEL_ERROR = 0.01
MIN_GRAD_COSINE = 0.99


def accuracy(data: bench.CaseData, cfg: bench.BenchConfig) -> list[dict]:
    """Label error and gradient cosine of every residual setting against the reference."""
    n = cfg.accuracy_rays
    batch = data.batch(n)
    ref_it = bench.load_integrator(data.boxes, "dense", True, cfg)
    ref = bench.labels_and_gradient(ref_it, bench.reference_chunks(ref_it, data, n, cfg))
    rows = []
    for name, sampling, residual, options in SETTINGS:
        if not residual:
            continue
        it = bench.load_integrator(data.boxes, sampling, residual, cfg, **options)
        labels, grad = bench.labels_and_gradient(it, iter([(lambda it=it: it.render_rays(batch.o, batch.d, batch.time),
                                                            batch.weights)]))
        err = bench.label_error(labels, ref[0])
        rows.append({"setting": name, **err, "grad_cosine": bench.cosine(grad, ref[1]),
                     "within_bounds": bool(err["max_abs"] <= MAX_LABEL_ERROR
                                           and bench.cosine(grad, ref[1]) >= MIN_GRAD_COSINE)})
        print(f"{name:30s}: max {err['max_abs']:.4f} p99 {err['p99_abs']:.4f} cos {rows[-1]['grad_cosine']:.4f}",
              flush=True)
    return rows


def plot(path: Path, timing: list[dict], title: str) -> None:
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    names = [t["setting"] for t in timing]
    ax.barh(names, [t["median_s"] for t in timing], color=["0.5"] + ["C0"] * (len(names) - 1))
    dense = timing[0]["median_s"]
    ax.axvline(dense / TARGET_SPEEDUP, color="C3", ls="--", label=f"dense / {TARGET_SPEEDUP:g} (target)")
    for i, t in enumerate(timing):
        ax.text(t["median_s"], i, f"  {t['median_s']:.3f} s ({dense / t['median_s']:.1f}x)", va="center", fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("forward + backward step (s), median")
    ax.set_xlim(0, dense * 1.35)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/residual_floor.json"))
    ap.add_argument("--instances", type=int, default=6)
    ap.add_argument("--rays", type=int, default=16384)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    cfg = bench.BenchConfig()
    start = time.perf_counter()
    data, _ = bench.case_data(cfg, args.instances, True)
    rows = accuracy(data, cfg)
    batch = data.batch(args.rays)
    runs = {name: bench.TimedIntegrator(bench.load_integrator(data.boxes, sampling, residual, cfg, **options), batch, cfg, seed=1)
            for name, sampling, residual, options in SETTINGS}
    seconds = side_by_side_steps(runs, args.repeats)
    dense = float(np.median(seconds["dense"]))
    timing = [{"setting": name, "residual": residual, "options": options, "median_s": float(np.median(seconds[name])),
               "runs_s": seconds[name], "speedup_vs_dense": dense / float(np.median(seconds[name]))}
              for name, _, residual, options in SETTINGS]
    for t in timing:
        print(f"{t['setting']:30s}: {t['median_s']:.3f} s, dense / this {t['speedup_vs_dense']:.2f}x")
    write_results(args.out, __doc__, time.perf_counter() - start, config={
        "instances": args.instances, "rays": args.rays, "repeats": args.repeats, "seed": bench.case_seed(cfg, args.instances, True),
        "sharpness": cfg.sharpness, "temperature": cfg.temperature, "accuracy_rays": cfg.accuracy_rays,
        "target_speedup": TARGET_SPEEDUP}, accuracy=rows, timing=timing)
    plot(args.out.with_suffix(".png"), timing,
         f"{args.instances} boxes, {args.rays} rays, residual field (dense: with it); side by side, {args.repeats} steps each")
    return 0


if __name__ == "__main__":
    sys.exit(main())
