"""Smoke tests of the scripts in examples/."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parents[1]
#: Generous: the first run compiles its Dr.Jit kernels (cached in ~/.drjit afterwards).
EXAMPLE_TIMEOUT_S = 900


def test_optimize_scene_runs_and_writes_renders(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, str(REPO / "examples" / "optimize_scene.py"), "--steps", "2", "--views", "2",
         "--scale", "0.05", "--preview-scale", "0.1", "--fit-size", "--out", str(out)],
        capture_output=True, text=True, timeout=EXAMPLE_TIMEOUT_S, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-4000:]
    for name in ("before.png", "after.png", "masks.png"):
        img = cv2.imread(str(out / name))
        assert img is not None, name
        assert img.shape == (38, 141, 3), (name, img.shape)  # 1408 x 376 at scale 0.1
    match = re.search(r"mean 3D IoU vs ground truth: ([0-9.]+) -> ([0-9.]+)", proc.stdout)
    assert match, proc.stdout
    assert all(0.0 <= float(v) <= 1.0 for v in match.groups())
    assert len(re.findall(r"^instance \d+: 3D IoU", proc.stdout, flags=re.M)) == 5  # target frame 3: 5 cars
