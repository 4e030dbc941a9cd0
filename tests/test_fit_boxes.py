"""``examples/fit_boxes.py`` with ``plugins/vsrd_plugins`` copied alone into another folder."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "fit_boxes.py"
#: The example's promise: under 2 minutes on 2 cores, and a mean 3D IoU of at least 0.9.
TIME_LIMIT_S = 120.0
IOU_MIN = 0.9
#: The only top-level modules the example may import (besides the standard library).
ALLOWED = {"mitsuba", "drjit", "numpy", "vsrd_plugins"}
#: Runs the example with a ``vsrd_mi`` that fails on import and checks where ``vsrd_plugins``
#: comes from (an installed copy of this repository must not stand in for the copied folder).
RUNNER = """
import runpy, sys
import vsrd_plugins
folder, script = sys.argv[1:3]
assert vsrd_plugins.__file__.startswith(folder), vsrd_plugins.__file__
sys.argv = [script]
runpy.run_path(script, run_name="__main__")
"""


def test_example_imports_only_mitsuba_drjit_numpy_and_the_plugins():
    tree = ast.parse(EXAMPLE.read_text())
    names = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
             for alias in node.names}
    names |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
              and node.module and node.level == 0}
    third_party = {n for n in names if n not in sys.stdlib_module_names}
    assert third_party == ALLOWED, third_party


def test_fit_boxes_runs_with_the_plugin_folder_alone(tmp_path):
    project = tmp_path / "project"
    shutil.copytree(REPO / "plugins" / "vsrd_plugins", project / "vsrd_plugins",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(EXAMPLE, project / "fit_boxes.py")
    blocker = tmp_path / "blocker" / "vsrd_mi"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError('the example must not need vsrd_mi')\n")
    env = {**os.environ, "PYTHONPATH": f"{project}{os.pathsep}{blocker.parent}"}
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", RUNNER, str(project), str(project / "fit_boxes.py")],
                          capture_output=True, text=True, cwd=project, env=env, timeout=10 * TIME_LIMIT_S)
    seconds = time.perf_counter() - start
    assert proc.returncode == 0, proc.stderr[-4000:]
    last = proc.stdout.strip().splitlines()[-1]
    match = re.fullmatch(r"mean 3D IoU of the fitted boxes vs the true ones: ([0-9.]+)", last)
    assert match, proc.stdout[-2000:]
    assert float(match.group(1)) >= IOU_MIN, proc.stdout[-2000:]
    assert seconds < TIME_LIMIT_S, seconds
