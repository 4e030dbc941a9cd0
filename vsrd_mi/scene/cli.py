"""``vsrd-mi export-scene``: write the Mitsuba XML scene of one KITTI-360 target frame."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dataclasses import replace

from ..data.kitti360 import Sequence
from ..data.observations import ObservationConfig, load_observations
from ..data.selection import SelectionConfig, spec_for_frame
from ..errors import DataError
from .builder import save_scene_xml
from .initial import default_initial_boxes


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export-scene`` sub-command."""
    p = subparsers.add_parser(
        "export-scene", help="write the Mitsuba XML scene (sensors + initial boxes) of a target frame",
        description="Select the source frames of FRAME, build one sensor per frame in the target's "
                    "optimisation frame and the vsrd_silhouette integrator holding default initial "
                    "boxes, and write it as Mitsuba XML (mi.load_file reads it after `import vsrd_mi`).")
    p.add_argument("root", type=Path, help="KITTI-360 root directory")
    p.add_argument("out", type=Path, help="output XML file")
    p.add_argument("--sequence", required=True, help="sequence number (0) or full name")
    p.add_argument("--frame", required=True, type=int, help="target frame index")
    p.add_argument("--min-sources", type=int, default=None,
                   help="fewest source frames accepted (default: SelectionConfig.min_sources)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Build and write the scene; a data problem is reported on stderr with exit code 2."""
    selection = SelectionConfig()
    if args.min_sources is not None:
        selection = replace(selection, min_sources=args.min_sources)
    try:
        seq = Sequence(args.root, args.sequence)
        obs = load_observations(seq, spec_for_frame(seq, args.frame, selection),
                                ObservationConfig(selection=selection))
    except DataError as exc:
        print(f"vsrd-mi export-scene: {exc}", file=sys.stderr)
        return 2
    save_scene_xml(args.out, obs, default_initial_boxes(obs))
    note = f" ({obs.spec.note})" if obs.spec is not None and obs.spec.note else ""
    print(f"{args.out}: {obs.num_frames} sensors, {obs.num_instances} instances, target {args.frame}{note}")
    return 0
