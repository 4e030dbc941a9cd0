"""The per-sequence batch manifest ``OUT/<sequence>/manifest.json``.

One entry per target frame (key: zero-padded frame index) records

* ``status``: ``running`` (handed to the executor, not finished: a process killed meanwhile
  leaves it so, and the next run computes it again), ``done``, ``skipped`` (the job found nothing
  to compute) or ``failed``;
* ``submitted`` / ``started`` / ``finished`` (ISO 8601, UTC), ``seconds``, ``attempts``;
* ``error``: ``{"type", "message", "traceback"}`` for failed targets, else ``null``;
* ``outputs``: ``[{"path", "bytes", "sha256"}]``, paths relative to ``OUT/<sequence>``;
* ``fingerprint``: :meth:`TargetTask.fingerprint` of the task that produced the entry.

The file is rewritten atomically (:mod:`vsrd_mi.batch.atomic`) after every change, only by the
process running the batch, which holds an exclusive lock (``.manifest.lock``, released by the
kernel when that process dies) so two batches cannot interleave on one output directory.

A target is *finished* (skipped on rerun) when its status is ``done`` or ``skipped``, its
fingerprint matches the task, and every output still exists with the recorded size and SHA-256
and parses (:func:`default_output_checks`).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from datetime import datetime, timezone
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from ..errors import DataError
from .atomic import TEMP_SUFFIX, atomic_write_json, temp_prefix
from .tasks import TargetResult, TargetTask

MANIFEST_NAME = "manifest.json"
LOCK_NAME = ".manifest.lock"
MANIFEST_FORMAT = "vsrd-mi-batch-manifest"
MANIFEST_VERSION = 1

#: Manifest statuses. ``running`` exists only in the manifest (never as a job result).
MANIFEST_STATUSES: tuple[str, ...] = ("running", "done", "skipped", "failed")
#: Statuses of a target that need not run again (provided its outputs check out).
FINISHED_STATUSES: tuple[str, ...] = ("done", "skipped")
#: ``error.type`` recorded when a job reports outputs that are missing or invalid.
OUTPUT_ERROR_TYPE = "OutputError"

#: Reads a file and raises if it does not parse; keyed by file suffix in the checks mapping.
OutputCheck = Callable[[Path], object]

_HASH_CHUNK_BYTES = 1 << 20


class ManifestError(DataError):
    """The manifest file is unreadable, malformed or belongs to another sequence."""


class ManifestLockedError(ManifestError):
    """Another process is running a batch on the same output directory."""


def _check_json(path: Path) -> object:
    def reject_constant(name: str) -> None:
        raise ValueError(f"non-finite number {name}")
    return json.loads(path.read_text(encoding="utf-8"), parse_constant=reject_constant)


def _check_text(path: Path) -> object:
    return path.read_bytes().decode("utf-8")


def _check_npy(path: Path) -> object:
    return np.load(path, allow_pickle=False)


def _check_npz(path: Path) -> object:
    with np.load(path, allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def default_output_checks() -> dict[str, OutputCheck]:
    """Parsers used to validate outputs by suffix: strict JSON, UTF-8 text, ``.npy``, ``.npz``.

    Files with other suffixes are checked by size and SHA-256 only. Pass a mapping with more
    (or stricter) entries, e.g. ``{".txt": vsrd_mi.data.kitti_labels.read_labels}``, to
    :func:`vsrd_mi.batch.run_batch` through :class:`vsrd_mi.batch.BatchConfig`.
    """
    return {".json": _check_json, ".txt": _check_text, ".npy": _check_npy, ".npz": _check_npz}


def utc_iso(timestamp: float | None) -> str | None:
    """POSIX time as ISO 8601 UTC with milliseconds (``None`` stays ``None``)."""
    if timestamp is None:
        return None
    return datetime.fromtimestamp(timestamp, timezone.utc).isoformat(timespec="milliseconds")


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(_HASH_CHUNK_BYTES), b""):
            digest.update(chunk)
    return digest.hexdigest()


def output_problem(sequence_dir: Path, relpath: str, checks: Mapping[str, OutputCheck],
                   expected: Mapping[str, Any] | None = None) -> str | None:
    """Why the output ``relpath`` (relative to ``sequence_dir``) is not valid, or ``None``.

    Checks that the path is relative and stays inside ``sequence_dir``, that the file exists,
    that it matches ``expected`` ``bytes`` / ``sha256`` when given, and that it parses with the
    check registered for its suffix.
    """
    pure = PurePosixPath(relpath)
    if pure.is_absolute() or Path(relpath).is_absolute() or ".." in pure.parts or not pure.parts:
        return f"output path {relpath!r} is not a relative path inside {sequence_dir}"
    path = sequence_dir / relpath
    if not path.is_file():
        return f"output {path} does not exist"
    if expected is not None:
        size = path.stat().st_size
        if size != expected.get("bytes"):
            return f"output {path} has {size} bytes, the manifest recorded {expected.get('bytes')}"
        if file_sha256(path) != expected.get("sha256"):
            return f"output {path} changed since it was written (SHA-256 differs)"
    check = checks.get(path.suffix.lower())
    if check is not None:
        try:
            check(path)
        except Exception as exc:  # any parse failure means the file is unusable
            return f"output {path} does not parse: {type(exc).__name__}: {exc}"
    return None


def _validate_document(path: Path, doc: Any, sequence: str | None) -> dict[str, dict[str, Any]]:
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise ManifestError(path, f"not a vsrd-mi batch manifest (expected format "
                                  f"{MANIFEST_FORMAT!r})")
    if doc.get("version") != MANIFEST_VERSION:
        raise ManifestError(path, f"unsupported manifest version {doc.get('version')!r} "
                                  f"(expected {MANIFEST_VERSION})")
    if sequence is not None and doc.get("sequence") != sequence:
        raise ManifestError(path, f"manifest is for sequence {doc.get('sequence')!r}, "
                                  f"not {sequence!r}")
    targets = doc.get("targets")
    if not isinstance(targets, dict):
        raise ManifestError(path, "'targets' is not an object")
    for key, entry in targets.items():
        if not isinstance(entry, dict) or entry.get("status") not in MANIFEST_STATUSES:
            raise ManifestError(path, f"target {key}: missing or unknown status")
        outputs = entry.get("outputs")
        if not isinstance(outputs, list) or not all(
                isinstance(o, dict) and isinstance(o.get("path"), str)
                and isinstance(o.get("bytes"), int) and isinstance(o.get("sha256"), str)
                for o in outputs):
            raise ManifestError(path, f"target {key}: 'outputs' must be a list of "
                                      "{path, bytes, sha256} objects")
    return targets


def read_manifest(path: str | os.PathLike, sequence: str | None = None) -> dict[str, Any]:
    """Read and validate a manifest file without locking it (for reports)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ManifestError(path, "manifest file does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(path, f"cannot read manifest: {exc}") from exc
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ManifestError(path, f"manifest is not valid JSON: {exc}") from exc
    _validate_document(path, doc, sequence)
    return doc


class Manifest:
    """The locked, in-memory manifest of one sequence; every change is saved atomically.

    Use as a context manager (or call :meth:`close`) to release the lock.
    """

    def __init__(self, sequence_dir: str | os.PathLike, sequence: str) -> None:
        self.sequence_dir = Path(sequence_dir)
        self.sequence = sequence
        self.path = self.sequence_dir / MANIFEST_NAME
        self.sequence_dir.mkdir(parents=True, exist_ok=True)
        self._lock_fd: int | None = os.open(self.sequence_dir / LOCK_NAME,
                                            os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.close()
            raise ManifestLockedError(self.path, "another vsrd-mi batch is running on this "
                                                 "output directory") from None
        try:
            self._remove_stale_temp_files()
            self.targets: dict[str, dict[str, Any]] = (
                read_manifest(self.path, sequence)["targets"] if self.path.exists() else {})
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Manifest:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        """Release the lock (idempotent)."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def _remove_stale_temp_files(self) -> None:
        for stale in self.sequence_dir.glob(temp_prefix(self.path) + "*" + TEMP_SUFFIX):
            stale.unlink(missing_ok=True)

    def save(self) -> None:
        """Write the manifest atomically."""
        atomic_write_json(self.path, {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION,
                                      "sequence": self.sequence, "targets": self.targets})

    def is_finished(self, task: TargetTask, checks: Mapping[str, OutputCheck]) -> bool:
        """Whether ``task`` is finished: see the module docstring."""
        entry = self.targets.get(task.key)
        if (entry is None or entry["status"] not in FINISHED_STATUSES
                or entry.get("fingerprint") != task.fingerprint()):
            return False
        return all(output_problem(self.sequence_dir, out["path"], checks, expected=out) is None
                   for out in entry["outputs"])

    def refresh_outputs(self, relpaths: Iterable[str]) -> list[str]:
        """Record the current size and SHA-256 of finished targets' outputs that a later step
        rewrote on purpose (the consensus's label files), so that a rerun still finds those
        targets finished; saves when anything changed. Returns the paths updated."""
        wanted = {PurePosixPath(Path(p)).as_posix() for p in relpaths}
        updated = []
        for entry in self.targets.values():
            for out in entry.get("outputs", []):
                path = self.sequence_dir / out["path"]
                if out["path"] in wanted and path.is_file():
                    out.update({"bytes": path.stat().st_size, "sha256": file_sha256(path)})
                    updated.append(out["path"])
        if updated:
            self.save()
        return updated

    def mark_running(self, task: TargetTask, when: float) -> None:
        """Record that ``task`` was handed to the executor at POSIX time ``when``; save."""
        previous = self.targets.get(task.key, {})
        self.targets[task.key] = {
            "frame": int(task.frame), "status": "running", "fingerprint": task.fingerprint(),
            "seed": int(task.seed), "attempts": int(previous.get("attempts", 0)) + 1,
            "submitted": utc_iso(when), "started": None, "finished": None, "seconds": None,
            "error": None, "outputs": []}
        self.save()

    def record(self, task: TargetTask, result: TargetResult,
               checks: Mapping[str, OutputCheck]) -> str:
        """Record ``result`` for ``task`` (after checking its outputs); save; return the status.

        A ``done``/``skipped`` result whose outputs are missing or do not parse is recorded as
        ``failed`` with error type :data:`OUTPUT_ERROR_TYPE`.
        """
        status, error = result.status, None
        if result.status == "failed":
            error = {"type": result.error_type or "Error", "message": result.error or "",
                     "traceback": result.traceback}
        outputs: list[dict[str, Any]] = []
        for relpath in result.outputs:
            problem = output_problem(self.sequence_dir, relpath, checks)
            if problem is not None:
                if status != "failed":
                    status = "failed"
                    error = {"type": OUTPUT_ERROR_TYPE, "message": problem, "traceback": None}
                continue
            path = self.sequence_dir / relpath
            outputs.append({"path": PurePosixPath(Path(relpath)).as_posix(),
                            "bytes": path.stat().st_size, "sha256": file_sha256(path)})
        entry = self.targets.setdefault(task.key, {"frame": int(task.frame), "attempts": 1,
                                                   "submitted": None})
        entry.update({"status": status, "fingerprint": task.fingerprint(),
                      "seed": int(task.seed), "started": utc_iso(result.started),
                      "finished": utc_iso(result.finished), "seconds": float(result.seconds),
                      "error": error, "outputs": outputs})
        self.save()
        return status

    def counts(self) -> dict[str, int]:
        """Number of targets per manifest status."""
        return dict(Counter(entry["status"] for entry in self.targets.values()))
