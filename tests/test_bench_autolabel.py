"""``vsrd-mi bench autolabel``: its pieces, the worker's isolation of a revision's code, and an
end-to-end run (slow)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from vsrd_mi.bench import autolabel as bench
from vsrd_mi.errors import DataError
from vsrd_mi.bench import autolabel_worker as worker
from vsrd_mi.data.kitti360 import sequence_name
from vsrd_mi.synth.suites import MANIFEST, SUITE_FORMAT, suite

REPO = Path(__file__).resolve().parents[1]


def test_middle_targets():
    assert bench.middle([1, 2, 3, 4, 5, 6, 7], 3) == [3, 4, 5]
    assert bench.middle([1, 2], 3) == [1, 2]
    assert bench.middle([1, 2, 3], 0) == [1, 2, 3]


def test_data_specs_are_checked(tmp_path):
    assert bench.data_sequences("bundled", tmp_path) == [("bundled", REPO / "scenes" / "kitti360-synth", 0)]
    for bad in ("synth:1,2", "synth:a,b,c", "kitti:1,2,3", "bundle"):
        with pytest.raises(ValueError, match="expected 'suite:SET"):
            bench.data_sequences(bad, tmp_path)
    with pytest.raises(ValueError, match="expected 'suite:validation'"):
        bench.data_sequences("suite:testing", tmp_path)
    # a given root is only read: nothing is generated into it
    with pytest.raises(DataError, match="does not write into a given root"):
        bench.data_sequences(f"suite:validation:long@{tmp_path}", tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_suite_data_times_the_first_round_only(tmp_path):
    # a written root's manifest stands in for its sequences: a given root is only read
    rounds = [m for m in suite("validation") if m.scenario.name == "tight_rows"]
    assert len(rounds) > 1
    manifest = {"format": SUITE_FORMAT, "sequences": {sequence_name(m.sequence): {} for m in rounds}}
    (tmp_path / MANIFEST).write_text(json.dumps(manifest))
    got = bench.data_sequences(f"suite:validation:tight_rows@{tmp_path}", tmp_path)
    assert got == [("validation/tight_rows", tmp_path.resolve(), rounds[0].sequence)]


def test_differing_label_files_are_listed(tmp_path):
    a, b = tmp_path / "a" / "seq" / "labels", tmp_path / "b" / "seq" / "labels"
    a.mkdir(parents=True)
    b.mkdir(parents=True)
    (a / "0000000001.txt").write_text("Car 0 0 1\n")
    (b / "0000000001.txt").write_text("Car 0 0 1\n")
    assert bench.labels_identical(tmp_path / "a", tmp_path / "b") == []
    (b / "0000000001.txt").write_text("Car 0 0 2\n")
    (a / "0000000002.txt").write_text("Car\n")
    assert bench.labels_identical(tmp_path / "a", tmp_path / "b") == ["seq/labels/0000000002.txt",
                                                                      "seq/labels/0000000001.txt"]


def test_worker_imports_only_the_tree_on_the_path(tmp_path):
    """A tree without ``vsrd_mi.autolabel`` (as at ed219dd) must not get the installed checkout's."""
    tree = tmp_path / "tree"
    (tree / "vsrd_mi" / "optimise").mkdir(parents=True)
    (tree / "vsrd_mi" / "__init__.py").write_text("")
    (tree / "vsrd_mi" / "optimise" / "__init__.py").write_text("")
    (tree / "vsrd_mi" / "optimise" / "autolabel.py").write_text("WHERE = 'tree'\n")
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import autolabel_worker as w; w.only_the_path(); "
            "m = w.first_module(w.JOB_MODULES); print(m.WHERE, m.__name__, w.foreign_modules('vsrd_mi'))")
    env = {"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-P", "-c", code, str(Path(worker.__file__).parent)],
                         capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["tree", "vsrd_mi.optimise.autolabel", "[]"]


def test_kernel_steps_count_new_and_compiled_jit_kernels():
    class FakeDr:
        class KernelType:
            JIT, Memset = "jit", "memset"

        def __init__(self):
            self.batches = [[], [{"type": "jit", "cache_hit": 0}, {"type": "jit", "cache_hit": 1, "cache_disk": 1},
                                 {"type": "memset"}]]
            self.batches += [[{"type": "jit", "cache_hit": 1, "cache_disk": 0}, {"type": "memset"}]] * worker.WARMUP_STEPS
            self.batches += [[{"type": "jit", "cache_hit": 1, "cache_disk": 1}]]

        def kernel_history(self):
            return self.batches.pop(0)

    steps = worker.KernelSteps(FakeDr())
    for _ in range(worker.WARMUP_STEPS + 2):
        steps.step()
    s = steps.summary()
    assert (s["new_in_warmup"], s["compiled_in_warmup"]) == (2, 1)
    assert (s["new_after_warmup"], s["compiled_after_warmup"]) == (1, 0)
    assert s["steps_with_new_kernels"] == [worker.WARMUP_STEPS + 1]
    assert s["launched_per_step"] == pytest.approx(1.5)


@pytest.mark.slow
def test_bench_runs_both_sides_and_reports(tmp_path):
    """Two rounds of this checkout against its own HEAD on one short target."""
    out = tmp_path / "bench"
    proc = subprocess.run(
        [sys.executable, "-m", "vsrd_mi", "bench", "autolabel", "--data", "bundled", "--max-targets", "1",
         "--rounds", "2", "--rev", "HEAD", "--set", "steps=12", "--set", "warmup_steps=4",
         "--out", str(out), "--work-dir", str(tmp_path / "work")],
        capture_output=True, text=True, cwd=REPO, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads((out / "autolabel.json").read_text())
    assert set(result["summary"]) == {"this", "HEAD"}
    for side in result["summary"].values():
        assert side["seconds_per_target"] > 0 and side["steps_per_target"] == 12
        assert side["kernels"]["launched_per_step"] > 0 and side["peak_rss_mib"] > 0
        assert 0.0 <= side["mean_iou_3d_all"] <= 1.0
    assert result["comparison"]["speedup_total"] > 0
    assert all(not d["differing_label_files"] for d in result["deterministic"].values())


def test_register_adds_the_command():
    parser = argparse.ArgumentParser()
    bench.register(parser.add_subparsers())
    args = parser.parse_args(["autolabel", "--rev", "ed219dd", "--cold", "--sequence"])
    assert (args.rev, args.cold, args.sequence, args.rounds) == ("ed219dd", True, bench.DEFAULT_SEQUENCE, 2)
    assert parser.parse_args(["autolabel"]).sequence is None
