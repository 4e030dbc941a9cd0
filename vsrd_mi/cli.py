"""The ``vsrd-mi`` command line.

Each pipeline stage owns its sub-commands: a module listed in :data:`SUBCOMMAND_MODULES` defines
``register(subparsers)`` which adds its parser(s) and sets ``func`` to a callable taking the parsed
``argparse.Namespace`` and returning an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import sys

#: Modules contributing sub-commands, in the order they appear in ``vsrd-mi --help``.
SUBCOMMAND_MODULES: tuple[str, ...] = (
    "vsrd_mi.scene.cli",
    "vsrd_mi.synth.cli",
    "vsrd_mi.synth.suite_cli",
    "vsrd_mi.autolabel.cli",
    "vsrd_mi.init.cli",
    "vsrd_mi.evaluate.cli",
    "vsrd_mi.export.cli",
    "vsrd_mi.batch.cli",
    "vsrd_mi.bench.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vsrd-mi",
        description="Multi-view 3D box autolabeling (VSRD++) on Mitsuba 3 / Dr.Jit.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
