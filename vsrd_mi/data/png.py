"""Strict PNG reading: one clear :class:`~vsrd_mi.errors.DataError` for every bad file.

OpenCV silently returns ``None`` (or, for some truncations, a partly decoded image) for damaged
files, so the chunk structure is checked first: signature, every chunk's length and CRC, and a
final ``IEND`` chunk. The pixel data is then decoded by OpenCV and its bit depth, channel count and
size are checked against what the caller expects.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from ..errors import DataError

#: The 8-byte PNG file signature.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png_structure(path: Path, data: bytes) -> None:
    """Raise :class:`DataError` unless ``data`` is a structurally complete PNG file."""
    if not data.startswith(PNG_SIGNATURE):
        raise DataError(path, "not a PNG file (bad signature)")
    pos = len(PNG_SIGNATURE)
    while True:
        if pos + 12 > len(data):
            raise DataError(path, "truncated PNG (file ends before the IEND chunk)")
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        chunk_type = data[pos + 4:pos + 8]
        end = pos + 12 + length
        if end > len(data):
            raise DataError(path, f"truncated PNG (chunk {chunk_type!r} runs past the end of the file)")
        (crc,) = struct.unpack(">I", data[end - 4:end])
        if zlib.crc32(data[pos + 4:end - 4]) & 0xFFFFFFFF != crc:
            raise DataError(path, f"corrupt PNG (CRC mismatch in chunk {chunk_type!r})")
        if chunk_type == b"IEND":
            return
        pos = end


def read_png(path: str | Path, *, dtype: type, channels: int,
             size: tuple[int, int] | None = None, what: str = "image") -> np.ndarray:
    """Read a PNG and check its format.

    Args:
        path: the file.
        dtype: required sample type (``np.uint8`` for 8-bit, ``np.uint16`` for 16-bit).
        channels: 1 for a single-channel image (returned as HxW), 3 for colour (returned as HxWx3 RGB).
        size: required ``(width, height)``, or None to accept any size.
        what: a short name for the image used in error messages ("instance map", ...).

    Raises:
        DataError: missing file, damaged file, wrong bit depth, wrong channel count, wrong size.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DataError(path, f"missing {what} file") from None
    except OSError as exc:
        raise DataError(path, f"cannot read {what}: {exc.strerror or exc}") from None
    check_png_structure(path, data)
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(path, f"corrupt PNG ({what} could not be decoded)")
    if img.dtype != dtype:
        bits = 8 * np.dtype(img.dtype).itemsize
        want = 8 * np.dtype(dtype).itemsize
        raise DataError(path, f"{what} is {bits}-bit, expected {want}-bit")
    got_channels = 1 if img.ndim == 2 else img.shape[2]
    if got_channels != channels:
        raise DataError(path, f"{what} has {got_channels} channel(s), expected {channels}")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise DataError(path, f"{what} is {img.shape[1]}x{img.shape[0]} pixels, "
                              f"expected {size[0]}x{size[1]}")
    if channels == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img
