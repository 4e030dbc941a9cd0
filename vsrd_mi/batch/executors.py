"""Executors: run a job over tasks and yield ``(task, result)`` as each target completes.

* :class:`InProcessExecutor` runs targets one after another in the calling process.
* :class:`DaskExecutor` submits one Dask task per target to a ``distributed`` cluster: a
  :class:`distributed.LocalCluster` it starts (worker processes, loopback only, one thread each)
  or an existing scheduler it connects to. Only the parent (the caller) sees results; workers
  never touch the manifest.

Both call the job through :func:`execute_task`, which turns exceptions into ``failed`` results and
times the call, so a target behaves the same under either executor.
"""

from __future__ import annotations

import logging
import os
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from typing import Protocol

from .tasks import TargetResult, TargetTask

#: A job: an importable top-level function (Dask pickles it by reference).
Process = Callable[[TargetTask], TargetResult]
#: Called by an executor right before a target is handed to a worker.
OnSubmit = Callable[[TargetTask], None]


def error_type_name(exc: BaseException) -> str:
    """``QualName`` for builtin exceptions, ``module.QualName`` for the others."""
    cls = type(exc)
    if cls.__module__ == "builtins":
        return cls.__qualname__
    return f"{cls.__module__}.{cls.__qualname__}"


def failed_result(exc: BaseException, *, with_traceback: bool = True) -> TargetResult:
    """A ``failed`` :class:`TargetResult` describing ``exc``."""
    return TargetResult(status="failed", error=str(exc) or repr(exc),
                        error_type=error_type_name(exc),
                        traceback=traceback.format_exc() if with_traceback else None)


def execute_task(process: Process, task: TargetTask) -> TargetResult:
    """Run ``process(task)``; any exception becomes a ``failed`` result; fill in the timing.

    The returned result's ``seconds``, ``started`` and ``finished`` are measured here (whatever
    the job put there is replaced). A job returning something other than a
    :class:`TargetResult` is a failure (``TypeError``).
    """
    started = time.time()
    t0 = time.perf_counter()
    try:
        result = process(task)
        if not isinstance(result, TargetResult):
            raise TypeError(f"job {getattr(process, '__qualname__', process)!r} returned "
                            f"{type(result).__name__}, expected TargetResult")
    except Exception as exc:  # a failing target must not stop the batch
        result = failed_result(exc)
    return replace(result, seconds=time.perf_counter() - t0, started=started,
                   finished=time.time())


class Executor(Protocol):
    """Runs ``process`` over ``tasks``, yielding each ``(task, result)`` as it completes."""

    def run(self, process: Process, tasks: Iterable[TargetTask],
            on_submit: OnSubmit) -> Iterator[tuple[TargetTask, TargetResult]]:
        ...


class InProcessExecutor:
    """Runs targets sequentially in this process (the default)."""

    def run(self, process: Process, tasks: Iterable[TargetTask],
            on_submit: OnSubmit) -> Iterator[tuple[TargetTask, TargetResult]]:
        for task in tasks:
            on_submit(task)
            yield task, execute_task(process, task)


@dataclass(frozen=True)
class DaskConfig:
    """Settings of :class:`DaskExecutor`.

    Attributes:
        workers: worker processes of the local cluster (``None``: one per CPU core); ignored
            when ``scheduler`` is given.
        scheduler: address of an existing scheduler, e.g. ``tcp://10.0.0.5:8786``; ``None``
            starts a local cluster on the loopback interface.
        threads_per_worker: threads per local worker process (a job is single-threaded Python
            driving Dr.Jit's own thread pool, so one task per process).
        host: interface the local cluster listens on (loopback only by default).
        dashboard_address: local cluster dashboard address (``None``: no dashboard).
        pending_per_thread: tasks kept submitted per worker thread; more tasks are submitted
            as results come back, so the parent never holds futures for the whole batch.
        connect_timeout_s: seconds to wait for an existing scheduler.
        log_level: level of the ``distributed`` loggers of a local cluster.
    """

    workers: int | None = None
    scheduler: str | None = None
    threads_per_worker: int = 1
    host: str = "127.0.0.1"
    dashboard_address: str | None = None
    pending_per_thread: int = 2
    connect_timeout_s: float = 30.0
    log_level: int = logging.WARNING

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"DaskConfig.workers must be >= 1, got {self.workers}")
        if self.threads_per_worker < 1 or self.pending_per_thread < 1:
            raise ValueError("DaskConfig.threads_per_worker and pending_per_thread must be >= 1")


class DaskExecutor:
    """One Dask task per target on a local or existing ``distributed`` cluster."""

    def __init__(self, config: DaskConfig | None = None) -> None:
        self.config = config or DaskConfig()

    def run(self, process: Process, tasks: Iterable[TargetTask],
            on_submit: OnSubmit) -> Iterator[tuple[TargetTask, TargetResult]]:
        from distributed import Client, LocalCluster, as_completed

        cfg = self.config
        if cfg.scheduler is not None:
            try:
                client = Client(cfg.scheduler, timeout=cfg.connect_timeout_s)
            except (OSError, TimeoutError) as exc:
                raise ConnectionError(f"cannot connect to the Dask scheduler at "
                                      f"{cfg.scheduler}: {exc}") from exc
            cluster = None
        else:
            # without a dashboard the scheduler still serves health/metrics over HTTP: put that
            # on a free port of the same interface instead of the default 8787
            http = {} if cfg.dashboard_address is not None else {
                "dashboard_address": f"{cfg.host}:0"}
            cluster = LocalCluster(n_workers=cfg.workers or os.cpu_count() or 1,
                                   threads_per_worker=cfg.threads_per_worker, processes=True,
                                   host=cfg.host, dashboard_address=cfg.dashboard_address,
                                   scheduler_kwargs=http, silence_logs=cfg.log_level)
            client = Client(cluster)
        try:
            yield from self._run_on(client, as_completed, process, iter(tasks), on_submit)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()

    def _run_on(self, client, as_completed, process: Process, tasks: Iterator[TargetTask],
                on_submit: OnSubmit) -> Iterator[tuple[TargetTask, TargetResult]]:
        in_flight: dict[str, TargetTask] = {}
        pending = as_completed()

        def window() -> int:
            threads = sum(client.nthreads().values())
            return max(1, threads) * self.config.pending_per_thread

        def top_up() -> None:
            limit = window()
            while len(in_flight) < limit:
                task = next(tasks, None)
                if task is None:
                    return
                on_submit(task)
                future = client.submit(execute_task, process, task, pure=False)
                in_flight[future.key] = task
                pending.add(future)

        top_up()
        for future in pending:
            task = in_flight.pop(future.key)
            try:
                result = future.result()
            except Exception as exc:  # worker died, (un)pickling failed, ...
                result = failed_result(exc, with_traceback=False)
            del future  # drop the parent's reference so the cluster can free the result
            yield task, result
            top_up()
