"""KITTI object label files: parsing, formatting, atomic writing, conversion to/from :class:`Box3D`.

One object per line (``docs/method.md`` §9)::

    type truncated occluded alpha x1 y1 x2 y2 h w l x y z ry [score]

``(x, y, z)`` is the centre of the box's *bottom* face in the rectified camera frame (y down),
``(h, w, l)`` its full height, width and length, ``ry`` the KITTI yaw (heading along the object's
local +x), which relates to our yaw by ``ry = yaw - pi/2``
(:func:`vsrd_mi.geometry.boxes.kitti_ry_from_yaw`), and ``alpha = ry - atan2(x, z)`` the
observation angle, both wrapped to ``[-pi, pi)``. The 2D box ``(x1, y1, x2, y2)`` is in pixels.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..batch.atomic import atomic_write_text
from ..errors import DataError
from ..geometry.boxes import Box3D, kitti_ry_from_yaw, wrap_angle, yaw_from_kitti_ry

#: Number of whitespace-separated values on a label line without / with the trailing score.
N_FIELDS_NO_SCORE = 15
N_FIELDS_WITH_SCORE = 16

#: Decimals written for every float. Six decimals (micrometres, micro-radians, micro-pixels) make
#: a box -> label -> text -> label -> box round trip exact to 5e-7 in every parameter.
DEFAULT_DECIMALS = 6

#: KITTI class name of cars, the only class vsrd-mi labels and evaluates.
CAR = "Car"


#: ``truncated`` / ``occluded`` written for pseudo labels (not estimated; 0 = fully visible).
DEFAULT_TRUNCATED = 0.0
DEFAULT_OCCLUDED = 0


@dataclass(frozen=True)
class KittiLabel:
    """One line of a KITTI label file (fields in file order; see the module docstring)."""

    type: str
    truncated: float
    occluded: int
    alpha: float
    box2d: tuple[float, float, float, float]
    h: float
    w: float
    l: float  # noqa: E741  (KITTI's field name)
    x: float
    y: float
    z: float
    ry: float
    score: float | None = None

    @property
    def height_2d(self) -> float:
        """Height of the 2D box in pixels (``y2 - y1``)."""
        return float(self.box2d[3] - self.box2d[1])


def parse_label_line(line: str, path: str | os.PathLike = "<string>", lineno: int = 0) -> KittiLabel:
    """Parse one label line; raises :class:`DataError` naming ``path`` and ``lineno`` when malformed.

    A line must hold 15 values (no score) or 16 (with score); every value but the type must be a
    finite number and ``occluded`` an integer.
    """
    where = f"line {lineno}"
    parts = line.split()
    if len(parts) not in (N_FIELDS_NO_SCORE, N_FIELDS_WITH_SCORE):
        raise DataError(path, f"{where}: expected {N_FIELDS_NO_SCORE} or {N_FIELDS_WITH_SCORE} "
                              f"values (type trunc occ alpha x1 y1 x2 y2 h w l x y z ry [score]), "
                              f"got {len(parts)}: {line.strip()!r}")
    try:
        values = [float(p) for p in parts[1:]]
    except ValueError as exc:
        raise DataError(path, f"{where}: not a number ({exc}): {line.strip()!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise DataError(path, f"{where}: non-finite value: {line.strip()!r}")
    if not values[1].is_integer():
        raise DataError(path, f"{where}: 'occluded' must be an integer, got {parts[2]!r}")
    return KittiLabel(
        type=parts[0], truncated=values[0], occluded=int(values[1]), alpha=values[2],
        box2d=(values[3], values[4], values[5], values[6]),
        h=values[7], w=values[8], l=values[9], x=values[10], y=values[11], z=values[12],
        ry=values[13], score=values[14] if len(values) == N_FIELDS_WITH_SCORE - 1 else None)


def read_labels(path: str | os.PathLike) -> list[KittiLabel]:
    """Read a label file (blank lines are skipped); raises :class:`DataError` on any bad input."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except FileNotFoundError:
        raise DataError(path, "label file not found") from None
    except IsADirectoryError:
        raise DataError(path, "is a directory, not a label file") from None
    except UnicodeDecodeError as exc:
        raise DataError(path, f"not a text label file (non-ASCII byte at offset {exc.start})") from None
    except OSError as exc:
        raise DataError(path, f"cannot read label file: {exc.strerror}") from None
    return [parse_label_line(line, path, i) for i, line in enumerate(text.splitlines(), start=1)
            if line.strip()]


def format_label_line(label: KittiLabel, decimals: int = DEFAULT_DECIMALS) -> str:
    """Format one label as a line (no newline); the score is written when it is not None."""
    if not label.type or any(c.isspace() for c in label.type):
        raise ValueError(f"label type must be one non-empty word, got {label.type!r}")
    floats = [label.truncated]
    tail = [label.alpha, *label.box2d, label.h, label.w, label.l, label.x, label.y, label.z,
            label.ry]
    if label.score is not None:
        tail.append(label.score)
    if not all(math.isfinite(v) for v in floats + tail):
        raise ValueError(f"cannot write a label with non-finite values: {label}")
    fmt = f"{{:.{decimals}f}}"
    return " ".join([label.type, fmt.format(label.truncated), str(int(label.occluded))]
                    + [fmt.format(v) for v in tail])


def write_labels(path: str | os.PathLike, labels: Iterable[KittiLabel],
                 decimals: int = DEFAULT_DECIMALS) -> None:
    """Write a label file atomically.

    Through :func:`vsrd_mi.batch.atomic.atomic_write_text` (temporary file in the destination
    directory, fsync, :func:`os.replace`, directory fsync), so readers see either the old file or
    the complete new one. An empty ``labels`` writes an empty file (no objects).
    """
    path = Path(path)
    text = "".join(format_label_line(lab, decimals) + "\n" for lab in labels)
    atomic_write_text(path, text, encoding="ascii")


def observation_angle(ry: float, x: float, z: float) -> float:
    """KITTI observation angle ``alpha = ry - atan2(x, z)``, wrapped to ``[-pi, pi)``."""
    return float(wrap_angle(ry - math.atan2(x, z)))


def label_from_box(box: Box3D, box2d: Sequence[float], score: float | None = None,
                   type: str = CAR, truncated: float = DEFAULT_TRUNCATED,
                   occluded: int = DEFAULT_OCCLUDED) -> KittiLabel:
    """The KITTI label of ``box`` (in the rectified camera frame) with 2D box ``box2d``."""
    if len(box2d) != 4:
        raise ValueError(f"box2d must be (x1, y1, x2, y2), got {box2d!r}")
    x, y, z = (float(v) for v in box.bottom_centre)
    ry = kitti_ry_from_yaw(box.yaw)
    w, h, l = (float(v) for v in box.size)  # noqa: E741
    return KittiLabel(type=type, truncated=float(truncated), occluded=int(occluded),
                      alpha=observation_angle(ry, x, z),
                      box2d=tuple(float(v) for v in box2d),  # type: ignore[arg-type]
                      h=h, w=w, l=l, x=x, y=y, z=z, ry=ry,
                      score=None if score is None else float(score))


def box_from_label(label: KittiLabel) -> Box3D:
    """The :class:`Box3D` (rectified camera frame, static) described by ``label``.

    Raises ``ValueError`` for labels without a valid box (e.g. ``DontCare`` lines with negative
    dimensions).
    """
    centre = np.array([label.x, label.y - 0.5 * label.h, label.z])
    return Box3D(centre=centre, size=(label.w, label.h, label.l), yaw=yaw_from_kitti_ry(label.ry))
