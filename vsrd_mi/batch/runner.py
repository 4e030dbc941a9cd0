"""Run many targets, resumably: :func:`run_batch`.

For every sequence among the tasks the runner locks and loads ``OUT/<sequence>/manifest.json``
(:class:`~vsrd_mi.batch.manifest.Manifest`), skips finished targets, marks each remaining target
``running`` when it is handed to the executor and records its result as soon as it comes back;
the manifest is rewritten atomically after every change. A failing target (the job raised, e.g.
a non-finite loss, or its outputs are missing/corrupt) is recorded with its error and the batch
goes on. A killed run leaves its in-flight targets ``running``: the next run computes them again.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from tqdm import tqdm

from .executors import DaskConfig, DaskExecutor, Executor, InProcessExecutor, Process
from .manifest import Manifest, OutputCheck, default_output_checks
from .tasks import TargetTask

log = logging.getLogger(__name__)

ExecutorName = Literal["inprocess", "dask"]
EXECUTOR_NAMES: tuple[str, ...] = ("inprocess", "dask")


@dataclass(frozen=True)
class BatchConfig:
    """Batch settings beyond the executor choice.

    Attributes:
        output_checks: parser per output-file suffix used to decide whether a finished target's
            outputs are intact (see :func:`~vsrd_mi.batch.manifest.default_output_checks`).
        dask: settings of the Dask executor (its ``workers`` / ``scheduler`` are overridden by
            the arguments of :func:`run_batch` when those are given).
    """

    output_checks: Mapping[str, OutputCheck] = field(default_factory=default_output_checks)
    dask: DaskConfig = field(default_factory=DaskConfig)


@dataclass
class BatchSummary:
    """Counts of one :func:`run_batch` call (no per-target results are kept).

    Attributes:
        done: targets computed successfully in this run.
        failed: targets that failed in this run.
        skipped: targets not computed: already finished in the manifest, or the job reported
            ``skipped``.
        failed_targets: ``"<sequence>/<frame key>"`` of the failed targets.
    """

    done: int = 0
    failed: int = 0
    skipped: int = 0
    failed_targets: list[str] = field(default_factory=list)

    @property
    def total(self) -> int:
        """All targets of the batch."""
        return self.done + self.failed + self.skipped

    def exit_code(self) -> int:
        """Process exit code: 0 when no target failed, 1 otherwise."""
        return 0 if self.failed == 0 else 1

    def __str__(self) -> str:
        return (f"{self.total} targets: {self.done} done, {self.failed} failed, "
                f"{self.skipped} skipped")


def exit_code(summary: BatchSummary) -> int:
    """Process exit code of a batch: 0 when no target failed, 1 otherwise."""
    return summary.exit_code()


def make_executor(executor: ExecutorName, *, workers: int | None = None,
                  scheduler: str | None = None, dask: DaskConfig | None = None) -> Executor:
    """Build the executor named ``executor`` (``workers``/``scheduler`` apply to ``dask``)."""
    if executor == "inprocess":
        if workers is not None or scheduler is not None:
            raise ValueError("workers/scheduler need executor='dask'")
        return InProcessExecutor()
    if executor == "dask":
        base = dask or DaskConfig()
        return DaskExecutor(replace(
            base, workers=workers if workers is not None else base.workers,
            scheduler=scheduler or base.scheduler))
    raise ValueError(f"unknown executor {executor!r}; expected one of {EXECUTOR_NAMES}")


def _check_unique(tasks: list[TargetTask]) -> None:
    seen: set[tuple[Path, str]] = set()
    for task in tasks:
        ident = (task.sequence_dir.resolve(), task.key)
        if ident in seen:
            raise ValueError(f"target {task.sequence}/{task.key} appears twice in the batch")
        seen.add(ident)


def run_batch(tasks: Iterable[TargetTask], process: Process, *,
              executor: ExecutorName = "inprocess", workers: int | None = None,
              scheduler: str | None = None, progress: bool = True,
              config: BatchConfig | None = None) -> BatchSummary:
    """Run ``process`` on every unfinished task; record each outcome in its sequence manifest.

    Args:
        tasks: one :class:`TargetTask` per target frame (several sequences allowed; a target may
            appear once).
        process: the job, an importable top-level function (pickled by reference for Dask).
        executor: ``"inprocess"`` (sequential, default) or ``"dask"``.
        workers: number of local Dask worker processes (``executor='dask'`` only).
        scheduler: address of an existing Dask scheduler (``executor='dask'`` only).
        progress: show a progress bar.
        config: output checks and Dask settings.

    Returns:
        The :class:`BatchSummary`; :meth:`BatchSummary.exit_code` gives the process exit code.

    Raises:
        ManifestError: a manifest is corrupt, or another batch holds its lock.
        ValueError: a target appears twice, or the executor arguments are inconsistent.
    """
    cfg = config or BatchConfig()
    runner = make_executor(executor, workers=workers, scheduler=scheduler, dask=cfg.dask)
    task_list = list(tasks)
    _check_unique(task_list)
    summary = BatchSummary()
    with contextlib.ExitStack() as stack:
        manifests: dict[Path, Manifest] = {}
        for task in task_list:
            if task.sequence_dir.resolve() not in manifests:
                manifests[task.sequence_dir.resolve()] = stack.enter_context(
                    Manifest(task.sequence_dir, task.sequence))
        todo = []
        for task in task_list:
            if manifests[task.sequence_dir.resolve()].is_finished(task, cfg.output_checks):
                summary.skipped += 1
            else:
                todo.append(task)
        del task_list
        bar = stack.enter_context(tqdm(total=summary.total + len(todo), initial=summary.skipped,
                                       disable=not progress, unit="target", desc="batch"))

        def on_submit(task: TargetTask) -> None:
            manifests[task.sequence_dir.resolve()].mark_running(task, time.time())

        # closing(): an error here shuts a Dask cluster down at once, not at garbage collection
        results = stack.enter_context(contextlib.closing(runner.run(process, todo, on_submit)))
        for task, result in results:
            manifest = manifests[task.sequence_dir.resolve()]
            status = manifest.record(task, result, cfg.output_checks)
            if status == "failed":
                summary.failed += 1
                summary.failed_targets.append(f"{task.sequence}/{task.key}")
                error = manifest.targets[task.key]["error"]
                log.warning("target %s/%s failed: %s: %s", task.sequence, task.key,
                            error["type"], error["message"])
            elif status == "skipped":
                summary.skipped += 1
            else:
                summary.done += 1
            bar.update(1)
            bar.set_postfix(done=summary.done, failed=summary.failed, skipped=summary.skipped)
    return summary
