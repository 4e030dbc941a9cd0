"""``vsrd-mi bench BENCH ...``: benchmarks that measure what they compare side by side in one run.

Each module in :data:`BENCH_MODULES` defines ``register(subparsers)``, adding its own sub-command
under ``vsrd-mi bench`` (a parser whose ``func`` takes the parsed arguments and returns an exit
code), the same convention as :mod:`vsrd_mi.cli`.
"""

from __future__ import annotations

import argparse
import importlib

#: Modules contributing ``vsrd-mi bench`` sub-commands, in ``--help`` order.
BENCH_MODULES: tuple[str, ...] = (
    "vsrd_mi.bench.integrator",
    "vsrd_mi.bench.integrator_features",
    "vsrd_mi.bench.residual_scenes",
    "vsrd_mi.bench.residual_trained",
    "vsrd_mi.bench.autolabel",
    "vsrd_mi.bench.init_accuracy",
    "vsrd_mi.bench.memory",
    "vsrd_mi.bench.real_sample",
    "vsrd_mi.bench.validation",
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bench", help="benchmarks (timings and accuracy measured side by side in one run)",
        description="Benchmarks; results as JSON (plus CSV and a plot where the benchmark has them).")
    sub = parser.add_subparsers(dest="bench", metavar="BENCH")
    sub.required = True
    for name in BENCH_MODULES:
        importlib.import_module(name).register(sub)
