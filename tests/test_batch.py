"""Resumable batch runs: manifest, skipping, reruns, failures, atomic writes, batch-status CLI."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from batch_jobs import CALLS_LOG, digest_job, read_stats, samples_for, samples_path, stats_path
from vsrd_mi.batch import (Manifest, ManifestError, ManifestLockedError, TargetResult,
                           TargetTask, atomic_write_bytes, atomic_write_json, atomic_write_text,
                           exit_code, run_batch)
from vsrd_mi.batch.cli import executor_kwargs
from vsrd_mi.cli import main

SEQ = "2013_05_28_drive_0000_sync"


def make_tasks(out: Path, frames, seq: str = SEQ, seed: int = 7, **config) -> list[TargetTask]:
    return [TargetTask(root="/nonexistent/dataset", sequence=seq, frame=f, output_dir=str(out),
                       config=dict(config), seed=seed) for f in frames]


def calls(out: Path, seq: str = SEQ) -> list[int]:
    path = out / seq / CALLS_LOG
    return [int(line) for line in path.read_text().split()] if path.exists() else []


def manifest_targets(out: Path, seq: str = SEQ) -> dict:
    return json.loads((out / seq / "manifest.json").read_text())["targets"]


def check_outputs_match_reference(out: Path, tasks: list[TargetTask]) -> None:
    for task in tasks:
        ref = samples_for(task)
        stats = read_stats(out / task.sequence, task.frame)
        assert stats["mean"] == pytest.approx(float(ref.mean()), rel=0, abs=1e-12)
        np.testing.assert_array_equal(np.load(out / task.sequence / samples_path(task.frame)), ref)


# ----------------------------------------------------------------------------- atomic writes


def test_atomic_writes_replace_and_leave_no_temp_files(tmp_path):
    target = tmp_path / "sub" / "a.json"
    atomic_write_json(target, {"x": 1})
    atomic_write_json(target, {"x": [1.5, 2]})
    assert json.loads(target.read_text()) == {"x": [1.5, 2]}
    atomic_write_text(tmp_path / "b.txt", "héllo\n")
    assert (tmp_path / "b.txt").read_bytes() == "héllo\n".encode()
    atomic_write_bytes(tmp_path / "c.bin", b"\x00\x01")
    assert (tmp_path / "c.bin").read_bytes() == b"\x00\x01"
    leftovers = [p.name for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    assert leftovers == []


def test_atomic_json_rejects_nan_and_keeps_old_file(tmp_path):
    target = tmp_path / "a.json"
    atomic_write_json(target, {"ok": 1})
    with pytest.raises(ValueError, match=r"a\.json"):
        atomic_write_json(target, {"loss": float("nan")})
    assert json.loads(target.read_text()) == {"ok": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


# ----------------------------------------------------------------------------- resumability


def test_run_records_manifest_and_rerun_skips_finished(tmp_path):
    tasks = make_tasks(tmp_path, range(5))
    summary = run_batch(tasks, digest_job, progress=False)
    assert (summary.done, summary.failed, summary.skipped) == (5, 0, 0)
    assert summary.exit_code() == 0 and exit_code(summary) == 0
    assert sorted(calls(tmp_path)) == list(range(5))
    check_outputs_match_reference(tmp_path, tasks)

    targets = manifest_targets(tmp_path)
    assert sorted(targets) == [f"{f:010d}" for f in range(5)]
    for frame in range(5):
        entry = targets[f"{frame:010d}"]
        assert entry["status"] == "done" and entry["error"] is None and entry["attempts"] == 1
        assert entry["started"] <= entry["finished"] and entry["seconds"] >= 0
        assert [o["path"] for o in entry["outputs"]] == [stats_path(frame), samples_path(frame)]
        for out in entry["outputs"]:
            data = (tmp_path / SEQ / out["path"]).read_bytes()
            assert out["bytes"] == len(data)
            assert out["sha256"] == hashlib.sha256(data).hexdigest()

    again = run_batch(tasks, digest_job, progress=False)
    assert (again.done, again.failed, again.skipped) == (0, 0, 5)
    assert sorted(calls(tmp_path)) == list(range(5))  # the job was not called again


def test_damaged_outputs_make_done_targets_rerun(tmp_path):
    tasks = make_tasks(tmp_path, range(6))
    run_batch(tasks, digest_job, progress=False)
    seq_dir = tmp_path / SEQ
    truncated = seq_dir / stats_path(1)
    truncated.write_bytes(truncated.read_bytes()[:10])          # corrupt JSON
    (seq_dir / samples_path(2)).unlink()                        # missing
    edited = seq_dir / stats_path(3)                            # parses, but not what was written
    edited.write_text(json.dumps({**json.loads(edited.read_text()), "mean": 123.0}))
    garbage = seq_dir / samples_path(4)                         # same size, unreadable npy
    garbage.write_bytes(b"\xff" * garbage.stat().st_size)

    summary = run_batch(tasks, digest_job, progress=False)
    assert (summary.done, summary.failed, summary.skipped) == (4, 0, 2)
    assert sorted(calls(tmp_path)) == sorted(list(range(6)) + [1, 2, 3, 4])
    check_outputs_match_reference(tmp_path, tasks)
    assert manifest_targets(tmp_path)[f"{1:010d}"]["attempts"] == 2


def test_target_left_running_is_rerun(tmp_path):
    tasks = make_tasks(tmp_path, range(3))
    run_batch(tasks, digest_job, progress=False)
    path = tmp_path / SEQ / "manifest.json"
    doc = json.loads(path.read_text())
    doc["targets"][f"{1:010d}"]["status"] = "running"
    path.write_text(json.dumps(doc))
    summary = run_batch(tasks, digest_job, progress=False)
    assert (summary.done, summary.skipped) == (1, 2)
    assert manifest_targets(tmp_path)[f"{1:010d}"]["status"] == "done"


def test_changed_seed_or_config_reruns(tmp_path):
    run_batch(make_tasks(tmp_path, range(3), seed=1), digest_job, progress=False)
    new_seed = make_tasks(tmp_path, range(3), seed=2)
    assert run_batch(new_seed, digest_job, progress=False).done == 3
    check_outputs_match_reference(tmp_path, new_seed)
    new_config = make_tasks(tmp_path, range(3), seed=2, n=64)
    assert run_batch(new_config, digest_job, progress=False).done == 3
    check_outputs_match_reference(tmp_path, new_config)
    assert run_batch(new_config, digest_job, progress=False).skipped == 3


def test_several_sequences_get_their_own_manifest(tmp_path):
    tasks = make_tasks(tmp_path, [0, 1], seq="seq_a") + make_tasks(tmp_path, [0, 5], seq="seq_b")
    summary = run_batch(tasks, digest_job, progress=False)
    assert summary.done == 4
    assert sorted(manifest_targets(tmp_path, "seq_a")) == ["0000000000", "0000000001"]
    assert sorted(manifest_targets(tmp_path, "seq_b")) == ["0000000000", "0000000005"]
    check_outputs_match_reference(tmp_path, tasks)


# ----------------------------------------------------------------------------- failures


def test_failing_targets_are_recorded_and_the_batch_goes_on(tmp_path):
    tasks = make_tasks(tmp_path, range(6), fail_frames=[1], nan_frames=[4], lie_frames=[5])
    summary = run_batch(tasks, digest_job, progress=False)
    assert (summary.done, summary.failed, summary.skipped) == (3, 3, 0)
    assert summary.exit_code() == 1
    assert summary.failed_targets == [f"{SEQ}/{f:010d}" for f in (1, 4, 5)]
    targets = manifest_targets(tmp_path)
    err1 = targets[f"{1:010d}"]["error"]
    assert targets[f"{1:010d}"]["status"] == "failed"
    assert err1["type"] == "RuntimeError" and "synthetic failure at frame 1" in err1["message"]
    assert "digest_job" in err1["traceback"]
    err4 = targets[f"{4:010d}"]["error"]
    assert err4["type"] == "FloatingPointError" and "non-finite" in err4["message"]
    err5 = targets[f"{5:010d}"]["error"]
    assert err5["type"] == "OutputError" and "missing.json" in err5["message"]
    check_outputs_match_reference(tmp_path, [t for t in tasks if t.frame in (0, 2, 3)])

    # failed targets run again next time, finished ones do not
    again = run_batch(tasks, digest_job, progress=False)
    assert (again.done, again.failed, again.skipped) == (0, 3, 3)
    assert targets[f"{1:010d}"]["attempts"] == 1
    assert manifest_targets(tmp_path)[f"{1:010d}"]["attempts"] == 2


def _returns_wrong_type(task: TargetTask):
    return {"status": "done"}


def test_job_returning_wrong_type_fails(tmp_path):
    summary = run_batch(make_tasks(tmp_path, [0]), _returns_wrong_type, progress=False)
    assert summary.failed == 1
    assert manifest_targets(tmp_path)[f"{0:010d}"]["error"]["type"] == "TypeError"


def test_job_reported_skip_counts_as_finished(tmp_path):
    tasks = make_tasks(tmp_path, range(3), skip_frames=[2])
    summary = run_batch(tasks, digest_job, progress=False)
    assert (summary.done, summary.failed, summary.skipped) == (2, 0, 1)
    assert manifest_targets(tmp_path)[f"{2:010d}"]["status"] == "skipped"
    assert run_batch(tasks, digest_job, progress=False).skipped == 3
    assert sorted(calls(tmp_path)) == [0, 1, 2]


def test_result_status_and_task_config_are_validated(tmp_path):
    with pytest.raises(ValueError, match="status"):
        TargetResult(status="ok")
    for bad in ({"lr": float("nan")}, {"path": tmp_path}):
        with pytest.raises(ValueError, match="plain JSON"):
            make_tasks(tmp_path, [0], **bad)[0].fingerprint()


# ----------------------------------------------------------------------------- bad input / locking


@pytest.mark.parametrize("content, problem", [
    ("{not json", "not valid JSON"),
    ('{"format": "something-else"}', "not a vsrd-mi batch manifest"),
    ('{"format": "vsrd-mi-batch-manifest", "version": 99}', "unsupported manifest version"),
    ('{"format": "vsrd-mi-batch-manifest", "version": 1, "sequence": "other", "targets": {}}',
     "not '" + SEQ + "'"),
    ('{"format": "vsrd-mi-batch-manifest", "version": 1, "sequence": "' + SEQ
     + '", "targets": {"0000000000": {"status": "great", "outputs": []}}}', "unknown status"),
    ('{"format": "vsrd-mi-batch-manifest", "version": 1, "sequence": "' + SEQ
     + '", "targets": {"0000000000": {"status": "done", "outputs": [{"path": 3}]}}}', "outputs"),
])
def test_bad_manifest_raises_manifest_error(tmp_path, content, problem):
    path = tmp_path / SEQ / "manifest.json"
    path.parent.mkdir(parents=True)
    path.write_text(content)
    with pytest.raises(ManifestError, match=problem) as info:
        run_batch(make_tasks(tmp_path, [0]), digest_job, progress=False)
    assert info.value.path == str(path)
    assert calls(tmp_path) == []


def test_second_batch_on_same_output_is_refused(tmp_path):
    with Manifest(tmp_path / SEQ, SEQ):
        with pytest.raises(ManifestLockedError, match="another vsrd-mi batch"):
            run_batch(make_tasks(tmp_path, [0]), digest_job, progress=False)
    assert run_batch(make_tasks(tmp_path, [0]), digest_job, progress=False).done == 1


def test_same_directory_spelled_differently_shares_one_manifest(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    tasks = make_tasks(Path("out"), [0]) + make_tasks(Path("./out/../out"), [1])
    assert run_batch(tasks, digest_job, progress=False).done == 2
    assert sorted(manifest_targets(tmp_path / "out")) == ["0000000000", "0000000001"]


def test_duplicate_targets_and_bad_executor_arguments_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="appears twice"):
        run_batch(make_tasks(tmp_path, [0, 1, 0]), digest_job, progress=False)
    with pytest.raises(ValueError, match="executor"):
        run_batch(make_tasks(tmp_path, [0]), digest_job, executor="threads", progress=False)
    with pytest.raises(ValueError, match="dask"):
        run_batch(make_tasks(tmp_path, [0]), digest_job, workers=2, progress=False)


# ----------------------------------------------------------------------------- CLI


def test_batch_status_cli(tmp_path, capsys):
    assert main(["batch-status", str(tmp_path)]) == 2
    run_batch(make_tasks(tmp_path, range(3)), digest_job, progress=False)
    assert main(["batch-status", str(tmp_path)]) == 0
    assert "3 targets, 3 done" in capsys.readouterr().out
    run_batch(make_tasks(tmp_path, range(4), fail_frames=[3]), digest_job, progress=False)
    assert main(["batch-status", str(tmp_path), "--sequence", SEQ]) == 1
    out = capsys.readouterr().out
    assert "1 failed" in out and "0000000003 failed: RuntimeError" in out
    (tmp_path / SEQ / "manifest.json").write_text("[]")
    assert main(["batch-status", str(tmp_path)]) == 2
    assert "manifest.json" in capsys.readouterr().err


def test_executor_options_parse():
    import argparse
    from vsrd_mi.batch.cli import add_executor_arguments
    parser = argparse.ArgumentParser()
    add_executor_arguments(parser)
    assert executor_kwargs(parser.parse_args([])) == {
        "executor": "inprocess", "workers": None, "scheduler": None, "progress": True}
    assert executor_kwargs(parser.parse_args(["--workers", "3", "--no-progress"])) == {
        "executor": "dask", "workers": 3, "scheduler": None, "progress": False}
    assert executor_kwargs(parser.parse_args(["--scheduler", "tcp://h:1"]))["executor"] == "dask"
    for bad in (["--workers", "0"], ["--workers", "2", "--scheduler", "tcp://h:1"]):
        with pytest.raises(SystemExit):
            parser.parse_args(bad)
    # the spelling: --executor dask with --workers / --scheduler
    assert executor_kwargs(parser.parse_args(["--executor", "dask", "--workers", "2"]))["executor"] == "dask"
    assert executor_kwargs(parser.parse_args(["--executor", "dask", "--scheduler", "tcp://h:1"])) == {
        "executor": "dask", "workers": None, "scheduler": "tcp://h:1", "progress": True}
    assert executor_kwargs(parser.parse_args(["--executor", "inprocess"]))["executor"] == "inprocess"
    with pytest.raises(ValueError, match="--executor dask needs --workers N"):
        executor_kwargs(parser.parse_args(["--executor", "dask"]))
    with pytest.raises(ValueError, match="cannot be combined"):
        executor_kwargs(parser.parse_args(["--executor", "inprocess", "--workers", "2"]))
