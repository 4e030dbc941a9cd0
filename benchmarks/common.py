"""Shared pieces of the benchmark scripts in this folder (run as ``python benchmarks/<name>.py``,
which puts this folder on ``sys.path``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from vsrd_mi.bench.autolabel import DATASETS, ensure_dataset
from vsrd_mi.optimise.config import SHAPE_PRIOR_FIELDS

#: The bundled example scene.
BUNDLED = Path(__file__).resolve().parent.parent / "scenes" / "kitti360-synth"
#: (dataset, target frame): the autolabel benchmark's targets and the bundled example's.
TARGETS = (("static-heavy", 11), ("static-heavy", 18), ("dynamic-heavy", 8), ("dynamic-heavy", 13),
           ("dynamic-heavy", 19), ("bundled", 14))


def dataset_root(name: str, data_dir: Path) -> Path:
    """Root of a benchmark dataset (generated on first use) or of the bundled scene."""
    if name == "bundled":
        return BUNDLED
    return ensure_dataset(data_dir, next(d for d in DATASETS if d.name == name))


def shape_prior_args(weight: float) -> list[str]:
    """``vsrd-mi autolabel`` arguments setting every size / yaw prior weight to ``weight``."""
    return [arg for k in SHAPE_PRIOR_FIELDS for arg in ("--set", f"weights.{k}={weight:g}")]


def write_results(path: Path, doc: str | None, elapsed: float, **fields) -> None:
    """The script's results as JSON: its purpose (the docstring's first paragraph), the command
    line, the elapsed seconds and ``fields``."""
    path.write_text(json.dumps({"purpose": (doc or "").split("\n\n")[0], "command": " ".join(sys.argv),
                                "elapsed_seconds": elapsed, **fields}, indent=1))
