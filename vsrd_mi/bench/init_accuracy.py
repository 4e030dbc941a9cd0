"""Accuracy of the 3D attribute initialisation (VSRD++ §III-D) on synthetic KITTI-360 sequences.

For every seed a sequence is generated with :func:`vsrd_mi.synth.generate_sequence`
(cached under ``--data-dir``), target frames are selected as the pipeline does
(:func:`vsrd_mi.data.selection.select_targets`, docs/method.md §5), and
:func:`vsrd_mi.init.sequence.initialise_target` initialises every target instance from the
target and its source frames (SGBM depth). Ground truth is read only here, for scoring, after the
initialisation has run:

* centre error (3D and bird's-eye) for *unoccluded cars within 30 m*: ground-truth centre depth
  <= ``--max-depth`` m, ground-truth box entirely inside the image, and the tight box of the
  instance mask overlapping the projected ground-truth box with IoU >= ``--unoccluded-iou``
  (an occluded or clipped car's mask covers only part of that box);
* dynamic-flag accuracy over all target instances;
* heading error of moving cars (angle between the initial yaw's length axis and the true one,
  in [0, 180] degrees: a moving car must also face the right way);
* speed error (m/s) of moving cars, and the apparent speed of parked cars.

Usage::

    vsrd-mi bench init-accuracy --seeds 0 1 2 --frames 50 --json benchmarks/init_accuracy.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..data.kitti360 import Sequence, sequence_name
from ..data.masks import tight_box
from ..data.observations import opt_from_world
from ..data.selection import select_targets
from ..geometry.boxes import wrap_angle
from ..geometry.boxes2d import iou
from ..geometry.camera import box_to_2d, image_bounds
from ..init.config import InitConfig
from ..init.sequence import initialise_target
from ..synth import SynthConfig, generate_sequence

#: Acceptance targets of the task (medians / rates over all scored instances).
TARGETS = {"centre_error_median_m": 0.5, "dynamic_accuracy": 0.9,
           "heading_error_moving_median_deg": 10.0, "speed_error_moving_median_mps": 1.0}


def ensure_sequence(data_dir: Path, seed: int, frames: int, config: SynthConfig) -> Path:
    """Root of the synthetic sequence of ``seed`` (generated unless a finished one is cached)."""
    root = data_dir / f"seed{seed:03d}_f{frames}"
    done = root / "DONE"
    if not done.is_file():
        t = time.perf_counter()
        generate_sequence(root, seq=0, frames=frames, n_static=4, n_dynamic=2, seed=seed,
                          config=config)
        done.write_text(f"{time.perf_counter() - t:.1f} s\n")
    return root


def score_target(seq: Sequence, spec, inits: dict, frame_rate: float, args) -> list[dict]:
    """One record per target instance: its initialisation against the ground truth."""
    c2w = seq.cam0_to_world(spec.target)
    to_opt = opt_from_world(c2w) @ c2w                        # target camera -> optimisation frame
    truth = {b.instance_id: b for b in seq.ground_truth(spec.target)}
    masks = seq.car_instances(spec.target)
    K, size = seq.calibration.K, seq.calibration.image_size
    bounds = image_bounds(size)
    records = []
    for iid in spec.instance_ids:
        gt_cam = truth.get(iid)
        if gt_cam is None:
            continue
        gt = gt_cam.transformed(to_opt)
        proj = box_to_2d(gt_cam, K)
        inside = proj is not None and bool(np.all(proj[:2] >= bounds[:2]) and np.all(proj[2:] <= bounds[2:]))
        mask_box = tight_box(masks[iid]) if iid in masks else None
        overlap = float(iou(np.asarray(mask_box, float), proj)) if (inside and mask_box is not None) else 0.0
        rec = {"target": spec.target, "instance": iid, "gt_dynamic": bool(gt.dynamic),
               "gt_depth": float(gt_cam.centre[2]), "mask_iou": overlap,
               "unoccluded": bool(inside and overlap >= args.unoccluded_iou
                                  and gt_cam.centre[2] <= args.max_depth),
               "gt_speed_mps": float(np.linalg.norm(gt.velocity) * frame_rate),
               "initialised": iid in inits}
        init = inits.get(iid)
        if init is not None:
            rec.update({
                "dynamic": bool(init.dynamic),
                "centre_error": float(np.linalg.norm(init.centre - gt.centre)),
                "centre_error_bev": float(np.linalg.norm((init.centre - gt.centre)[[0, 2]])),
                "mean_error": float(np.linalg.norm(init.cloud_mean - gt.centre)),
                "heading_error_deg": float(np.degrees(abs(wrap_angle(init.yaw - gt.yaw)))),
                "axis_error_deg": float(np.degrees(abs(wrap_angle(2 * (init.yaw - gt.yaw)) / 2))),
                "speed_mps": float(np.linalg.norm(init.velocity) * frame_rate),
                "velocity_error_mps": float(np.linalg.norm(init.velocity - gt.velocity) * frame_rate),
                "n_points": int(init.n_points), "n_frames": len(init.clouds)})
            rec["speed_error_mps"] = abs(rec["speed_mps"] - rec["gt_speed_mps"])
        records.append(rec)
    return records


def summarise(records: list[dict]) -> dict:
    """Medians and rates of the records (see the module doc for the populations)."""
    def med(vals):
        return float(np.median(vals)) if len(vals) else None

    ini = [r for r in records if r["initialised"]]
    unocc = [r for r in ini if r["unoccluded"]]
    moving = [r for r in ini if r["gt_dynamic"]]
    parked = [r for r in ini if not r["gt_dynamic"]]
    return {
        "instances": len(records), "initialised": len(ini),
        "unoccluded_within_range": len(unocc), "moving": len(moving), "parked": len(parked),
        "centre_error_median_m": med([r["centre_error"] for r in unocc]),
        "centre_error_bev_median_m": med([r["centre_error_bev"] for r in unocc]),
        "centre_error_p90_m": float(np.percentile([r["centre_error"] for r in unocc], 90)) if unocc else None,
        "cloud_mean_error_median_m": med([r["mean_error"] for r in unocc]),
        "centre_error_all_median_m": med([r["centre_error"] for r in ini]),
        "dynamic_accuracy": float(np.mean([r["dynamic"] == r["gt_dynamic"] for r in ini])) if ini else None,
        "dynamic_recall": float(np.mean([r["dynamic"] for r in moving])) if moving else None,
        "static_specificity": float(np.mean([not r["dynamic"] for r in parked])) if parked else None,
        "heading_error_moving_median_deg": med([r["heading_error_deg"] for r in moving]),
        "axis_error_parked_median_deg": med([r["axis_error_deg"] for r in parked]),
        "speed_error_moving_median_mps": med([r["speed_error_mps"] for r in moving]),
        "velocity_error_moving_median_mps": med([r["velocity_error_mps"] for r in moving]),
        "apparent_speed_parked_median_mps": med([r["speed_mps"] for r in parked]),
        "apparent_speed_parked_p90_mps": (float(np.percentile([r["speed_mps"] for r in parked], 90))
                                          if parked else None),
    }


def run(seeds: list[int], frames: int, data_dir: Path, targets_per_seq: int, args,
        synth: SynthConfig | None = None, cfg: InitConfig | None = None) -> dict:
    """Generate / reuse the sequences, initialise the chosen targets and score them."""
    synth = synth or SynthConfig()
    cfg = cfg or InitConfig()
    records, per_seed, seconds = [], {}, []
    for seed in seeds:
        root = ensure_sequence(data_dir, seed, frames, synth)
        seq = Sequence(root, sequence_name(0))
        specs = select_targets(seq)
        if len(specs) > targets_per_seq:
            specs = [specs[i] for i in np.linspace(0, len(specs) - 1, targets_per_seq).round().astype(int)]
        seed_records = []
        for spec in specs:
            t = time.perf_counter()
            inits = initialise_target(seq, spec, cfg)
            seconds.append(time.perf_counter() - t)
            rs = score_target(seq, spec, inits, synth.rig.frame_rate, args)
            for r in rs:
                r["seed"] = seed
            seed_records += rs
        per_seed[seed] = summarise(seed_records)
        per_seed[seed]["targets"] = [s.target for s in specs]
        records += seed_records
        print(f"seed {seed}: {json.dumps(per_seed[seed])}", flush=True)
    overall = summarise(records)
    overall["seconds_per_target_median"] = float(np.median(seconds)) if seconds else None
    passed = {k: (overall[k] is not None and (overall[k] >= v if k == "dynamic_accuracy" else overall[k] <= v))
              for k, v in TARGETS.items()}
    return {"git_commit": _git_commit(), "seeds": seeds, "frames": frames,
            "targets_per_seq": targets_per_seq,
            "max_depth": args.max_depth, "unoccluded_iou": args.unoccluded_iou,
            "init_config": asdict(cfg), "targets": TARGETS, "passed": passed,
            "overall": overall, "per_seed": per_seed, "records": records}


def _git_commit() -> str | None:
    """HEAD of the repository holding this module (None outside a git checkout)."""
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, check=True,
                              capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("init-accuracy", help="accuracy of the stereo initialisation on synthetic sequences",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--frames", type=int, default=50, help="frames per generated sequence")
    p.add_argument("--targets-per-seq", type=int, default=4)
    p.add_argument("--data-dir", type=Path, default=Path("runs/bench-data/init"),
                   help="where generated sequences are cached")
    p.add_argument("--max-depth", type=float, default=30.0)
    p.add_argument("--unoccluded-iou", type=float, default=0.7)
    p.add_argument("--json", type=Path, default=Path("benchmarks/init_accuracy.json"))
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    result = run(args.seeds, args.frames, args.data_dir, args.targets_per_seq, args)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({"overall": result["overall"], "passed": result["passed"]}, indent=1))
    return 0 if all(result["passed"].values()) else 1
