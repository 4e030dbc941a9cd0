"""``vsrd-mi synth-suite``: write the development or validation set (see :mod:`.suites`)."""

from __future__ import annotations

import argparse
import sys

from ..errors import DataError
from .suites import SET_SEEDS, SuiteMember, write_suite
from .world import PlacementError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth-suite", help="write the synthetic development or validation set (one KITTI-360 "
                            "root, one sequence per preset and round)",
        description="Write every preset of a set, in each of its rounds, as a sequence of one "
                    "KITTI-360 root (development sequences 100-105; validation three rounds, "
                    "200-205, 210-215, 220-225; 'long', 109 / 209, only with --only long; "
                    "development-traffic: four more moving-traffic streets, 110-113). Tune on "
                    "development, report validation. A sequence whose manifest entry "
                    "(OUT/suite.json) matches and whose files are complete is kept.")
    p.add_argument("out", help="dataset root to write (created if missing)")
    p.add_argument("--set", required=True, choices=sorted(SET_SEEDS), dest="set_name",
                   help="which seed set")
    p.add_argument("--only", metavar="NAME", help="write only this preset (e.g. tight_rows, long)")
    p.add_argument("--rounds", type=int, help="only the first ROUNDS rounds (default: all)")
    p.add_argument("--force", action="store_true", help="write sequences again even when kept")
    p.add_argument("--mesh", action="append", default=None, metavar="PLY",
                   help="car mesh file (repeatable); default: the bundled CC0 meshes")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    def progress(member: SuiteMember, done: int, total: int) -> None:
        if not args.quiet:
            print(f"\r{member.scenario.name} (sequence {member.sequence}): {done}/{total} frames",
                  end="" if done < total else "\n", file=sys.stderr, flush=True)

    try:
        written = write_suite(args.out, args.set_name, args.only, args.force, args.mesh, progress,
                              args.rounds)
    except (DataError, PlacementError, ValueError) as exc:
        print(f"vsrd-mi synth-suite: error: {exc}", file=sys.stderr)
        return 2
    for member, seconds in written:
        state = "kept" if seconds is None else f"written in {seconds:.1f} s"
        print(f"{member.scenario.name}: sequence {member.sequence}, seed {member.seed}, "
              f"{member.scenario.frames} frames: {state}")
    return 0
