"""``vsrd-mi synth``: write a synthetic KITTI-360 sequence (see :mod:`vsrd_mi.synth`)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from ..errors import DataError
from .generate import SynthConfig, generate_sequence
from .world import PlacementError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth", help="generate a synthetic KITTI-360 sequence (stereo images, masks, 3D boxes)",
        description="Render a synthetic street in the KITTI-360 release layout: calibration, "
                    "poses, both rectified cameras, 16-bit instance maps and 3D boxes.")
    p.add_argument("out", help="dataset root to write (created if missing)")
    p.add_argument("--seq", type=int, default=0, help="sequence number (folder "
                   "2013_05_28_drive_%%04d_sync; default 0)")
    p.add_argument("--frames", type=int, default=60, help="number of frames (default 60)")
    p.add_argument("--static", type=int, default=4, help="parked cars (default 4)")
    p.add_argument("--dynamic", type=int, default=2, help="moving cars (default 2)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--first-frame", type=int, default=0, help="number of the first frame")
    p.add_argument("--mesh", action="append", default=None, metavar="PLY",
                   help="car mesh file (repeatable; metres, +Y up, front at +Z, origin at the "
                        "bottom centre); default: the bundled CC0 meshes")
    p.add_argument("--procedural-only", action="store_true",
                   help="use procedural car shapes only (no mesh files)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    meshes = [] if args.procedural_only else args.mesh
    config = replace(SynthConfig(), first_frame=args.first_frame)

    def progress(done: int, total: int) -> None:
        if not args.quiet:
            print(f"\rrendered {done}/{total} frames", end="" if done < total else "\n",
                  file=sys.stderr, flush=True)

    try:
        summary = generate_sequence(args.out, seq=args.seq, frames=args.frames,
                                    n_static=args.static, n_dynamic=args.dynamic, seed=args.seed,
                                    meshes=meshes, config=config, progress=progress)
    except (DataError, PlacementError, ValueError) as exc:
        print(f"vsrd-mi synth: error: {exc}", file=sys.stderr)
        return 2
    cars = summary.world.cars
    print(f"wrote {summary.sequence}: {len(summary.frames)} frames, {len(cars)} cars "
          f"({sum(c.dynamic for c in cars)} moving) to {summary.root} in {summary.seconds:.1f} s")
    return 0
