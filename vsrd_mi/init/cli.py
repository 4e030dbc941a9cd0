"""Sub-commands of the init stage.

* ``vsrd-mi init``: initial boxes (centre, yaw, velocity, dynamic flag, size) of the instances of
  one KITTI-360 target frame, from stereo depth (SGBM), a depth directory, or none; JSON output
  and optionally the pseudo point clouds as PLY.
* ``vsrd-mi stereo-depth``: SGBM depth maps of a sequence as ``%010d.png`` (uint16, metres * 256)
  or ``%010d.npy`` files, for reuse with ``vsrd-mi init --depth DIR``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..errors import DataError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``init`` and ``stereo-depth`` sub-commands."""
    p = subparsers.add_parser(
        "init", help="initialise 3D boxes of a target frame from stereo depth (VSRD++ III-D)",
        description="Select the source frames of FRAME, build per-instance pseudo point clouds from "
                    "depth, and estimate each target instance's centre, yaw, velocity and dynamic "
                    "flag in the target's optimisation frame. Writes JSON (and a PLY with --ply).")
    p.add_argument("root", type=Path, help="KITTI-360 root directory")
    p.add_argument("out", type=Path, help="output JSON file")
    p.add_argument("--sequence", required=True, help="sequence number (0) or full name")
    p.add_argument("--frame", required=True, type=int, help="target frame index")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--depth", type=Path, default=None, metavar="DIR",
                     help="directory of %%010d.png (uint16, m*256) or %%010d.npy (float m) depth maps "
                          "(default: OpenCV SGBM on the stereo pair)")
    src.add_argument("--no-depth", action="store_true",
                     help="no initialisation (writes an empty result; the optimiser uses default boxes)")
    p.add_argument("--ply", type=Path, default=None, help="also write the point clouds as PLY")
    p.add_argument("--dynamic-threshold", type=float, default=None, metavar="MPS",
                   help="speed (m/s) above which an instance is dynamic "
                        "(default: VelocityConfig.dynamic_speed_threshold)")
    p.set_defaults(func=run_init)

    d = subparsers.add_parser(
        "stereo-depth", help="write SGBM depth maps of a sequence (for `vsrd-mi init --depth`)",
        description="Run OpenCV semi-global matching on the rectified stereo pairs of a KITTI-360 "
                    "sequence and write metric depth maps named %%010d.png (uint16, metres * 256, "
                    "0 = invalid) or %%010d.npy (float32 metres, 0 = invalid).")
    d.add_argument("root", type=Path, help="KITTI-360 root directory")
    d.add_argument("out", type=Path, help="output directory")
    d.add_argument("--sequence", required=True, help="sequence number (0) or full name")
    d.add_argument("--frames", type=int, nargs=2, default=None, metavar=("FIRST", "LAST"),
                   help="inclusive frame range (default: every frame with a pose and images)")
    d.add_argument("--format", choices=("png", "npy"), default="png")
    d.add_argument("--wls", action="store_true", help="WLS-filter the disparity (cv2.ximgproc)")
    d.set_defaults(func=run_stereo_depth)


def init_result_json(target: int, inits: dict) -> dict:
    """JSON-ready description of :func:`~vsrd_mi.init.attributes.initialise`'s result."""
    out = {"target": target, "frame": "optimisation frame of the target (x right, y down, z forward)",
           "velocity_unit": "metres per frame index", "instances": {}}
    for iid, init in sorted(inits.items()):
        entry = init.to_box().to_dict()
        entry.update({"size_fitted": init.size is not None, "n_points": int(init.n_points),
                      "reference_offset": int(init.reference_offset),
                      "cloud_mean": np.asarray(init.cloud_mean).tolist(),
                      "n_velocity_pairs": int(init.n_velocity_pairs),
                      "velocity_standard_error": float(init.velocity_standard_error),
                      "velocity_effective_pairs": float(init.velocity_effective_pairs),
                      "points_per_frame": {str(o): len(c) for o, c in sorted(init.clouds.items())}})
        out["instances"][str(iid)] = entry
    return out


def run_init(args: argparse.Namespace) -> int:
    """Initialise one target frame; a data problem is reported on stderr with exit code 2."""
    from ..data.kitti360 import Sequence
    from ..data.selection import spec_for_frame
    from .attributes import save_point_clouds_ply
    from .config import InitConfig
    from .sequence import initialise_target

    cfg = InitConfig(depth_mode="none" if args.no_depth else ("dir" if args.depth else "sgbm"),
                     depth_dir=str(args.depth) if args.depth else None)
    if args.dynamic_threshold is not None:
        cfg.velocity.dynamic_speed_threshold = args.dynamic_threshold
    try:
        seq = Sequence(args.root, args.sequence)
        spec = spec_for_frame(seq, args.frame)
        inits = initialise_target(seq, spec, cfg)
    except DataError as exc:
        print(f"vsrd-mi init: {exc}", file=sys.stderr)
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(init_result_json(spec.target, inits), indent=1) + "\n")
    if args.ply is not None and inits:
        n = save_point_clouds_ply(args.ply, inits)
        print(f"{args.ply}: {n} points")
    n_dyn = sum(i.dynamic for i in inits.values())
    print(f"{args.out}: {len(inits)} of {len(spec.instance_ids)} instances initialised "
          f"({n_dyn} dynamic), target {spec.target}, {len(spec.sources)} sources")
    return 0


def run_stereo_depth(args: argparse.Namespace) -> int:
    """Write depth maps; a data problem is reported on stderr with exit code 2."""
    from ..data.kitti360 import Sequence
    from .config import StereoConfig
    from .depth import save_depth_png, stereo_depth

    try:
        seq = Sequence(args.root, args.sequence)
        frames = seq.frames if args.frames is None else [
            f for f in seq.frames if args.frames[0] <= f <= args.frames[1]]
        if not frames:
            raise DataError(seq.image_dir(0), "no frame with a pose and images in the range")
        args.out.mkdir(parents=True, exist_ok=True)
        calib, cfg = seq.calibration, StereoConfig(wls=args.wls)
        for f in frames:
            depth = stereo_depth(seq.image(f, 0), seq.image(f, 1), calib.K, calib.baseline, cfg)
            path = args.out / f"{f:010d}.{args.format}"
            if args.format == "png":
                save_depth_png(path, depth)
            else:
                np.save(path, np.nan_to_num(depth, nan=0.0).astype(np.float32))
    except DataError as exc:
        print(f"vsrd-mi stereo-depth: {exc}", file=sys.stderr)
        return 2
    print(f"{args.out}: {len(frames)} depth maps ({args.format})")
    return 0
