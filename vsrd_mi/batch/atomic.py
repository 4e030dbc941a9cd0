"""Crash-safe file writes: readers see either the old file or the complete new one.

Each writer puts the data into a temporary file in the destination directory, flushes and
``fsync``s it, renames it over the destination with :func:`os.replace` (atomic on POSIX within
one file system) and then ``fsync``s the directory so the rename itself survives a power loss.
A process killed mid-write leaves at most a stray ``.NAME.*.tmp`` file, never a truncated
``NAME``.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

#: Suffix of the temporary files (``.<name>.<random>.tmp``) written next to the destination.
TEMP_SUFFIX = ".tmp"


def temp_prefix(path: str | os.PathLike) -> str:
    """Prefix of the temporary files :func:`atomic_write_bytes` creates for ``path``."""
    return f".{Path(path).name}."


#: Permissions of written outputs (``mkstemp`` would leave them owner-only).
FILE_MODE = 0o644


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (creating parent directories); return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=temp_prefix(path), suffix=TEMP_SUFFIX)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp_name, FILE_MODE)
        os.replace(tmp_name, path)
    except BaseException as exc:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError) and exc.filename is None:  # e.g. ENOSPC from write()
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    fsync_directory(path.parent)
    return path


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically; return the path."""
    return atomic_write_bytes(path, text.encode(encoding))


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int | None = 1) -> Path:
    """Write ``obj`` as strict JSON (no NaN/Infinity) to ``path`` atomically; return the path.

    Raises ``ValueError`` naming ``path`` when ``obj`` holds a non-finite float or is not
    JSON-serialisable; nothing is written then.
    """
    try:
        text = json.dumps(obj, indent=indent, allow_nan=False, sort_keys=False)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: cannot write as JSON: {exc}") from exc
    return atomic_write_text(path, text + "\n")


def fsync_directory(directory: str | os.PathLike) -> None:
    """``fsync`` a directory so a rename inside it is durable (no-op where unsupported)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems cannot fsync directories; the rename is still atomic
    finally:
        os.close(fd)
