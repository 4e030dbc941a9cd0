"""Command-line pieces of batch runs.

* :func:`add_executor_arguments` / :func:`executor_kwargs`: the ``--executor`` / ``--workers`` / ``--scheduler`` /
  ``--no-progress`` options shared by batch sub-commands (e.g. ``vsrd-mi autolabel``), turned
  into keyword arguments of :func:`vsrd_mi.batch.run_batch`.
* ``vsrd-mi batch-status OUT``: prints what every ``OUT/<sequence>/manifest.json`` records
  (exit code 0 when every target is finished, 1 when some failed or were left running, 2 when a
  manifest is missing or corrupt).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from .manifest import FINISHED_STATUSES, MANIFEST_NAME, ManifestError, read_manifest


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def add_executor_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--workers N``, ``--scheduler ADDRESS`` and ``--no-progress`` to ``parser``."""
    group = parser.add_argument_group("batch execution")
    group.add_argument("--executor", choices=("inprocess", "dask"), default=None,
                       help="where targets run: in this process (the default) or on Dask; dask needs "
                            "--workers N (a local cluster) or --scheduler ADDRESS (an existing one)")
    where = group.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                       help="run targets on a local Dask cluster of N worker processes "
                            "(loopback only, one thread each); default: in this process")
    where.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                       help="run targets on an existing Dask cluster")
    group.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def executor_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of :func:`vsrd_mi.batch.run_batch` from the options added above.

    ``--workers`` / ``--scheduler`` imply ``--executor dask``; contradictory combinations raise
    :class:`ValueError` with the reason.
    """
    dask = args.workers is not None or args.scheduler is not None
    executor = getattr(args, "executor", None)
    if executor == "inprocess" and dask:
        raise ValueError("--executor inprocess cannot be combined with --workers or --scheduler")
    if executor == "dask" and not dask:
        raise ValueError("--executor dask needs --workers N (start a local cluster) or "
                         "--scheduler tcp://HOST:PORT (use an existing one)")
    return {"executor": "dask" if dask else "inprocess", "workers": args.workers,
            "scheduler": args.scheduler, "progress": not args.no_progress}


def format_status(manifest_path: Path, show_errors: bool = True) -> tuple[str, bool]:
    """Report of one manifest and whether all its targets are finished."""
    doc = read_manifest(manifest_path)
    targets = doc["targets"]
    counts: dict[str, int] = {}
    for entry in targets.values():
        counts[entry["status"]] = counts.get(entry["status"], 0) + 1
    lines = [f"{doc['sequence']}: {len(targets)} targets, "
             + ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))]
    if show_errors:
        for key, entry in sorted(targets.items()):
            if entry["status"] == "failed":
                error = entry.get("error") or {}
                lines.append(f"  {key} failed: {error.get('type')}: {error.get('message')}")
            elif entry["status"] == "running":
                lines.append(f"  {key} running (or left unfinished by an interrupted run)")
    finished = all(entry["status"] in FINISHED_STATUSES for entry in targets.values())
    return "\n".join(lines), finished


def _cmd_batch_status(args: argparse.Namespace) -> int:
    out = Path(args.output)
    if args.sequence:
        paths = [out / seq / MANIFEST_NAME for seq in args.sequence]
    else:
        paths = sorted(out.glob(f"*/{MANIFEST_NAME}"))
        if not paths:
            print(f"vsrd-mi batch-status: error: {out}: no */{MANIFEST_NAME} found",
                  file=sys.stderr)
            return 2
    all_finished = True
    try:
        for path in paths:
            text, finished = format_status(path, show_errors=not args.quiet)
            print(text)
            all_finished &= finished
    except ManifestError as exc:
        print(f"vsrd-mi batch-status: error: {exc}", file=sys.stderr)
        return 2
    return 0 if all_finished else 1


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``batch-status`` sub-command."""
    p = subparsers.add_parser(
        "batch-status", help="summarise the batch manifests under an output directory",
        description="Print the target counts per status of OUT/<sequence>/manifest.json and "
                    "list failed / unfinished targets. Exit code 0 when every target is "
                    "finished, 1 when some failed or are unfinished, 2 on a missing or "
                    "corrupt manifest.")
    p.add_argument("output", metavar="OUT", help="batch output directory")
    p.add_argument("--sequence", action="append", metavar="SEQ",
                   help="only this sequence (repeatable); default: every OUT/*/manifest.json")
    p.add_argument("--quiet", action="store_true", help="counts only, no per-target lines")
    p.set_defaults(func=_cmd_batch_status)
