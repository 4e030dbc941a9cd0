"""Dask executor: a loopback LocalCluster gives exactly the results of the in-process run."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

distributed = pytest.importorskip("distributed")

from batch_jobs import CALLS_LOG, digest_job  # noqa: E402
from vsrd_mi.batch import TargetTask, read_manifest, run_batch  # noqa: E402

SEQ = "2013_05_28_drive_0007_sync"
FRAMES = range(8)
CONFIG = {"n": 512, "fail_frames": [3], "nan_frames": [6]}
TESTS_DIR = str(Path(__file__).resolve().parent)


@pytest.fixture
def worker_import_path(monkeypatch):
    """Let spawned worker processes import ``batch_jobs`` (tests/ on their PYTHONPATH)."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        p for p in (TESTS_DIR, os.environ.get("PYTHONPATH")) if p))


def _tasks(out: Path) -> list[TargetTask]:
    return [TargetTask(root="/nonexistent", sequence=SEQ, frame=f, output_dir=str(out),
                       config=CONFIG, seed=5) for f in FRAMES]


def _snapshot(out: Path) -> tuple[dict, dict]:
    """Every output file's bytes, and each target's status, error type, outputs, fingerprint."""
    seq_dir = out / SEQ
    files = {str(p.relative_to(seq_dir)): p.read_bytes() for p in sorted(seq_dir.rglob("*"))
             if p.is_file() and p.parent != seq_dir}
    targets = read_manifest(seq_dir / "manifest.json", SEQ)["targets"]
    records = {k: (e["status"], (e["error"] or {}).get("type"), e["outputs"], e["fingerprint"])
               for k, e in targets.items()}
    return files, records


def test_local_cluster_matches_in_process_run(tmp_path, worker_import_path):
    ref = run_batch(_tasks(tmp_path / "seq"), digest_job, progress=False)
    summary = run_batch(_tasks(tmp_path / "dask"), digest_job, executor="dask", workers=2,
                        progress=False)
    assert (summary.done, summary.failed, summary.skipped) == (ref.done, ref.failed, ref.skipped)
    assert (summary.done, summary.failed) == (6, 2)
    assert sorted(summary.failed_targets) == sorted(ref.failed_targets)
    ref_files, ref_records = _snapshot(tmp_path / "seq")
    files, records = _snapshot(tmp_path / "dask")
    assert files.keys() == ref_files.keys() and len(files) == 12
    assert files == ref_files
    assert records == ref_records
    # the jobs really ran in other processes, once per target
    ran = (tmp_path / "dask" / SEQ / CALLS_LOG).read_text().split()
    assert sorted(map(int, ran)) == list(FRAMES)

    # resuming under Dask skips what is finished and reruns only the failed targets
    again = run_batch(_tasks(tmp_path / "dask"), digest_job, executor="dask", workers=2,
                      progress=False)
    assert (again.done, again.failed, again.skipped) == (0, 2, 6)


def test_existing_scheduler_and_dead_worker(tmp_path, worker_import_path):
    import dask
    # A worker death blames every task the scheduler had assigned to that worker (or whose
    # result it held, not yet reported): with one task per worker thread (saturation 1.0) and the
    # job dying only after the others have finished, only the dying job is blamed; with no
    # retries it fails at once.
    with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                          "distributed.scheduler.worker-saturation": 1.0}):
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                      host="127.0.0.1", dashboard_address=None,
                                      silence_logs=40) as cluster:
            config = {"n": 64, "die_frames": [2], "die_delay_s": 1.0}
            tasks = [TargetTask(root="/nonexistent", sequence=SEQ, frame=f,
                                output_dir=str(tmp_path), config=config, seed=1)
                     for f in range(4)]
            summary = run_batch(tasks, digest_job, executor="dask",
                                scheduler=cluster.scheduler_address, progress=False)
    assert (summary.done, summary.failed) == (3, 1)
    entry = read_manifest(tmp_path / SEQ / "manifest.json", SEQ)["targets"]["0000000002"]
    assert entry["status"] == "failed" and "KilledWorker" in entry["error"]["type"]
    stats = json.loads((tmp_path / SEQ / "stats" / "0000000003.json").read_text())
    assert stats["frame"] == 3


def test_unreachable_scheduler_is_a_clear_error(tmp_path):
    with pytest.raises(ConnectionError, match="tcp://127.0.0.1:9"):
        run_batch(_tasks(tmp_path)[:1], digest_job, executor="dask",
                  scheduler="tcp://127.0.0.1:9", progress=False,
                  config=_short_timeout())


def _short_timeout():
    from vsrd_mi.batch import BatchConfig, DaskConfig
    return BatchConfig(dask=DaskConfig(connect_timeout_s=2.0))
