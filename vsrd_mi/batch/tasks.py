"""What a batch runs: one :class:`TargetTask` per target frame, one :class:`TargetResult` back.

Both are plain, picklable dataclasses so that they travel unchanged to Dask workers. A job is any
importable top-level function ``process(task: TargetTask) -> TargetResult`` (for autolabeling:
:func:`vsrd_mi.autolabel.job.process_target`); it writes its outputs under
:attr:`TargetTask.sequence_dir` (atomically, e.g. with :mod:`vsrd_mi.batch.atomic`) and lists
them, relative to that directory, in :attr:`TargetResult.outputs`.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

#: Statuses a job may report. ``skipped`` means the job decided there is nothing to compute
#: for this target (e.g. no instance to optimise); it counts as finished like ``done``.
ResultStatus = Literal["done", "failed", "skipped"]
RESULT_STATUSES: tuple[str, ...] = ("done", "failed", "skipped")

#: Digits of the zero-padded frame index used as the manifest key (KITTI-360 file naming).
FRAME_KEY_DIGITS = 10


def frame_key(frame: int) -> str:
    """Manifest key of a target frame: the zero-padded index, e.g. ``0000000042``."""
    return f"{int(frame):0{FRAME_KEY_DIGITS}d}"


@dataclass(frozen=True)
class TargetTask:
    """One target frame of one sequence to process.

    Attributes:
        root: dataset root (KITTI-360 layout), readable by every worker.
        sequence: sequence name, e.g. ``2013_05_28_drive_0000_sync``.
        frame: target frame index.
        output_dir: output root ``OUT``; this target's files go under ``OUT/<sequence>/``.
        config: job configuration as a plain JSON-serialisable dict.
        seed: random seed of the job (a job must be deterministic given its task).
    """

    root: str
    sequence: str
    frame: int
    output_dir: str
    config: dict[str, Any] = field(default_factory=dict)
    seed: int = 0

    @property
    def key(self) -> str:
        """Manifest key of this target (see :func:`frame_key`)."""
        return frame_key(self.frame)

    @property
    def sequence_dir(self) -> Path:
        """``OUT/<sequence>``: where the job writes and the manifest lives."""
        return Path(self.output_dir) / self.sequence

    def fingerprint(self) -> str:
        """SHA-256 of what determines the job's result: sequence, frame, config and seed.

        The dataset root and output directory are left out so that moving either keeps finished
        targets valid; changing the config or the seed makes a finished target run again.
        """
        try:
            payload = json.dumps({"sequence": self.sequence, "frame": int(self.frame),
                                  "config": self.config, "seed": int(self.seed)},
                                 sort_keys=True, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"target {self.sequence}/{self.key}: the task config must be "
                             f"plain JSON with finite numbers ({exc})") from exc
        return hashlib.sha256(payload.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class TargetResult:
    """Outcome of one target.

    Attributes:
        status: ``done``, ``failed`` or ``skipped`` (see :data:`ResultStatus`).
        seconds: wall-clock seconds of the job call (filled in by the runner).
        outputs: files written, relative to :attr:`TargetTask.sequence_dir`.
        error: error message when ``failed``.
        error_type: exception type name when ``failed`` (``module.QualName`` for non-builtins).
        traceback: formatted traceback when the job raised.
        started: POSIX start time of the job call (filled in by the runner).
        finished: POSIX end time of the job call (filled in by the runner).
    """

    status: ResultStatus
    seconds: float = 0.0
    outputs: tuple[str, ...] = ()
    error: str | None = None
    error_type: str | None = None
    traceback: str | None = None
    started: float | None = None
    finished: float | None = None

    def __post_init__(self) -> None:
        if self.status not in RESULT_STATUSES:
            raise ValueError(f"TargetResult.status must be one of {RESULT_STATUSES}, "
                             f"got {self.status!r}")
        object.__setattr__(self, "outputs", tuple(str(p) for p in self.outputs))
