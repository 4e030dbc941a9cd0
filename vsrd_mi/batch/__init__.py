"""Resumable batch runs over many target frames, in-process or on a Dask cluster.

A batch is a list of :class:`TargetTask` (one per target frame) and a job
``process(task) -> TargetResult`` (for autolabeling
:func:`vsrd_mi.autolabel.job.process_target`).
:func:`run_batch` keeps ``OUT/<sequence>/manifest.json`` up to date after every target (status,
start/end time, seconds, error, outputs with size and SHA-256), skips targets that are already
finished with intact outputs, reruns targets a killed run left ``running``, records a failing
target and goes on, and returns a :class:`BatchSummary` (exit code 0 when nothing failed).
``vsrd-mi batch-status OUT`` prints the manifests' state.

Executors
---------
* in-process (default): targets run one after another.
* ``--workers N`` (``executor="dask", workers=N``): starts a ``distributed.LocalCluster`` of
  ``N`` worker processes with one thread each, listening on 127.0.0.1 only.
* ``--scheduler tcp://HOST:PORT`` (``executor="dask", scheduler=...``): uses an existing cluster.

Either way one Dask task is submitted per target (``client.submit(process, task, pure=False)``,
a few per worker thread at a time), results are gathered as they complete, and only the parent
process writes the manifest. A job is deterministic given its task (which carries the seed), so
results equal those of a sequential run.

Running on a real cluster
-------------------------
Every machine needs the same Python environment with vsrd-mi installed
(``pip install 'vsrd-mi[dask]'``), read access to the dataset at the same path (``--root``),
and the output directory ``OUT`` on a shared file system at the same path (jobs write their
outputs there; the parent checks them and writes the manifest). Then::

    # on the scheduler host (port 8786; the dashboard on 8787 is optional)
    dask scheduler --port 8786

    # on each worker host: one single-threaded worker process per core (Dr.Jit parallelises
    # inside a job); --nworkers may be lower to leave memory per job
    dask worker tcp://SCHEDULER_HOST:8786 --nworkers 8 --nthreads 1

    # anywhere that sees OUT: submit the batch
    vsrd-mi autolabel ... --scheduler tcp://SCHEDULER_HOST:8786

Keep the scheduler port reachable only from the cluster network (Dask executes whatever a client
submits). If the batch is interrupted, run the same command again: finished targets are skipped.
"""

from __future__ import annotations

from .atomic import atomic_write_bytes, atomic_write_json, atomic_write_text
from .executors import DaskConfig, DaskExecutor, InProcessExecutor, execute_task
from .manifest import (MANIFEST_NAME, Manifest, ManifestError, ManifestLockedError,
                       default_output_checks, read_manifest)
from .runner import BatchConfig, BatchSummary, exit_code, make_executor, run_batch
from .tasks import TargetResult, TargetTask, frame_key

__all__ = [
    "atomic_write_bytes", "atomic_write_json", "atomic_write_text",
    "DaskConfig", "DaskExecutor", "InProcessExecutor", "execute_task",
    "MANIFEST_NAME", "Manifest", "ManifestError", "ManifestLockedError",
    "default_output_checks", "read_manifest",
    "BatchConfig", "BatchSummary", "exit_code", "make_executor", "run_batch",
    "TargetResult", "TargetTask", "frame_key",
]
