"""``vsrd-mi synth``: write a synthetic KITTI-360 sequence (see :mod:`vsrd_mi.synth`)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from ..errors import DataError
from .generate import SynthConfig, generate_sequence
from .suites import LONG, SCENARIOS
from .world import PlacementError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth", help="generate a synthetic KITTI-360 sequence (stereo images, masks, 3D boxes)",
        description="Render a synthetic street in the KITTI-360 release layout: calibration, "
                    "poses, both rectified cameras, 16-bit instance maps and 3D boxes.")
    p.add_argument("out", help="dataset root to write (created if missing)")
    p.add_argument("--seq", type=int, default=0, help="sequence number (folder "
                   "2013_05_28_drive_%%04d_sync; default 0)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default 60, or "
                   "the preset's)")
    p.add_argument("--static", type=int, default=None, help="parked cars (default 4, or the "
                   "preset's; with a preset the most parked cars kept)")
    p.add_argument("--dynamic", type=int, default=None, help="moving cars (default 2, or the "
                   "preset's)")
    p.add_argument("--preset", choices=[s.name for s in SCENARIOS + (LONG,)], default=None,
                   help="use a suite preset's world (vehicle classes, parking rows, props, camera "
                        "pitch and roll; see docs/synthetic.md); default: the basic street")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--first-frame", type=int, default=0, help="number of the first frame")
    p.add_argument("--mesh", action="append", default=None, metavar="PLY",
                   help="car mesh file (repeatable; metres, +Y up, front at +Z, origin at the "
                        "bottom centre); default: the bundled CC0 meshes")
    p.add_argument("--procedural-only", action="store_true",
                   help="use procedural car shapes only (no mesh files)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


#: Frames, parked and moving cars of the basic street when no preset is given.
BASIC_COUNTS = (60, 4, 2)


def run(args: argparse.Namespace) -> int:
    meshes = [] if args.procedural_only else args.mesh
    preset = {s.name: s for s in SCENARIOS + (LONG,)}.get(args.preset)
    counts = BASIC_COUNTS if preset is None else (preset.frames, preset.n_static, preset.n_dynamic)
    frames, n_static, n_dynamic = (given if given is not None else default for given, default in
                                   zip((args.frames, args.static, args.dynamic), counts))
    config = replace(SynthConfig() if preset is None else preset.config,
                     first_frame=args.first_frame)

    def progress(done: int, total: int) -> None:
        if not args.quiet:
            print(f"\rrendered {done}/{total} frames", end="" if done < total else "\n",
                  file=sys.stderr, flush=True)

    try:
        summary = generate_sequence(args.out, seq=args.seq, frames=frames,
                                    n_static=n_static, n_dynamic=n_dynamic, seed=args.seed,
                                    meshes=meshes, config=config, progress=progress)
    except (DataError, PlacementError, ValueError) as exc:
        print(f"vsrd-mi synth: error: {exc}", file=sys.stderr)
        return 2
    cars = summary.world.cars
    print(f"wrote {summary.sequence}: {len(summary.frames)} frames, {len(cars)} cars "
          f"({sum(c.dynamic for c in cars)} moving) to {summary.root} in {summary.seconds:.1f} s")
    return 0
