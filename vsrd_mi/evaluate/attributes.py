"""Per-car attributes for the evaluation's breakdowns: the optional sidecar of a sequence.

A generator that knows more about its cars than KITTI-360's XML holds (vehicle class, how a parked
car stands, how much of it is hidden) writes ``<root>/data_3d_bboxes/train/<seq>.attributes.json``::

    {"format": "vsrd-mi attributes 1",
     "instances": {"26001": {"vehicle_class": "sedan", "dynamic": false,
                             "parking": "angled", "angle_to_road_deg": 30.0}},
     "frames": {"12": {"26001": {"occlusion": 0.42, "truncation": 0.0}}}}

Instance keys are instance-map values (``26 * 1000 + instanceId``) as strings, frame keys frame
indices as strings. ``parking`` is one of :data:`PARKING_KINDS` or null (moving cars);
``occlusion`` is ``1 - visible / amodal`` pixels of the car in the left image and ``truncation``
the share of its amodal silhouette outside the image, both in [0, 1]. Every field may be missing;
a missing file means no attributes (e.g. real KITTI-360), and every breakdown that needs one then
says so instead of guessing. A malformed file raises :class:`DataError` naming it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from ..data.kitti360 import sequence_name
from ..errors import DataError

#: Value of the sidecar's ``format`` key.
ATTRIBUTES_FORMAT = "vsrd-mi attributes 1"
#: Allowed values of ``parking`` (null = not parked).
PARKING_KINDS = ("parallel", "parallel_reversed", "angled", "perpendicular")


@dataclass(frozen=True)
class CarAttributes:
    """What the sidecar says about one ground-truth car in one frame (None: not known)."""

    vehicle_class: str | None = None
    dynamic: bool | None = None
    parking: str | None = None
    angle_to_road_deg: float | None = None
    occlusion: float | None = None
    truncation: float | None = None
    #: Not from the sidecar: the evaluation's measure of whether the views that label the car see
    #: its length (px, :func:`~vsrd_mi.evaluate.observability.length_view_shift`; with
    #: ``EvalConfig.length_views`` only).
    length_view_px: float | None = None


#: Attributes of a car the sidecar does not describe (or of every car without a sidecar).
UNKNOWN = CarAttributes()


def attributes_path(root: str | Path, sequence: int | str) -> Path:
    """``<root>/data_3d_bboxes/train/<sequence>.attributes.json``."""
    return Path(root) / "data_3d_bboxes" / "train" / f"{sequence_name(sequence)}.attributes.json"


@dataclass(frozen=True)
class SequenceAttributes:
    """The parsed sidecar of one sequence."""

    path: Path
    instances: dict[int, dict] = field(default_factory=dict)
    frames: dict[int, dict[int, dict]] = field(default_factory=dict)

    def lookup(self, frame: int, instance_value: int) -> CarAttributes:
        """Attributes of the car with instance-map value ``instance_value`` in ``frame``."""
        inst = self.instances.get(int(instance_value), {})
        seen = self.frames.get(int(frame), {}).get(int(instance_value), {})
        return CarAttributes(vehicle_class=inst.get("vehicle_class"), dynamic=inst.get("dynamic"),
                             parking=inst.get("parking"), angle_to_road_deg=inst.get("angle_to_road_deg"),
                             occlusion=seen.get("occlusion"), truncation=seen.get("truncation"))


def _check_number(path: Path, where: str, value, lo: float | None = None, hi: float | None = None) -> None:
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DataError(path, f"{where}: expected a finite number, got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise DataError(path, f"{where}: {value!r} is outside [{lo}, {hi}]")


def _int_key(path: Path, where: str, key: str) -> int:
    if not str(key).isdigit():
        raise DataError(path, f"{where}: key {key!r} is not a non-negative integer")
    return int(key)


def _instance(path: Path, key: str, entry) -> dict:
    where = f"instances[{key!r}]"
    if not isinstance(entry, dict):
        raise DataError(path, f"{where}: expected an object, got {type(entry).__name__}")
    vclass = entry.get("vehicle_class")
    if vclass is not None and (not isinstance(vclass, str) or not vclass):
        raise DataError(path, f"{where}.vehicle_class: expected a non-empty string, got {vclass!r}")
    if entry.get("dynamic") is not None and not isinstance(entry["dynamic"], bool):
        raise DataError(path, f"{where}.dynamic: expected true / false, got {entry['dynamic']!r}")
    if entry.get("parking") is not None and entry["parking"] not in PARKING_KINDS:
        raise DataError(path, f"{where}.parking: {entry['parking']!r} is not one of {PARKING_KINDS} or null")
    _check_number(path, f"{where}.angle_to_road_deg", entry.get("angle_to_road_deg"))
    return entry


def _seen(path: Path, frame_key: str, key: str, entry) -> dict:
    where = f"frames[{frame_key!r}][{key!r}]"
    if not isinstance(entry, dict):
        raise DataError(path, f"{where}: expected an object, got {type(entry).__name__}")
    for name in ("occlusion", "truncation"):
        _check_number(path, f"{where}.{name}", entry.get(name), 0.0, 1.0)
    return entry


def parse_attributes(path: str | Path, data: dict) -> SequenceAttributes:
    """Validate the sidecar's parsed JSON ``data`` (read from ``path``)."""
    path = Path(path)
    if not isinstance(data, dict) or data.get("format") != ATTRIBUTES_FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise DataError(path, f"not a sidecar of format {ATTRIBUTES_FORMAT!r} (format: {found!r})")
    raw_instances, raw_frames = data.get("instances", {}), data.get("frames", {})
    if not isinstance(raw_instances, dict) or not isinstance(raw_frames, dict):
        raise DataError(path, "'instances' and 'frames' must be objects")
    instances = {_int_key(path, "instances", k): _instance(path, k, v) for k, v in raw_instances.items()}
    frames: dict[int, dict[int, dict]] = {}
    for fk, cars in raw_frames.items():
        if not isinstance(cars, dict):
            raise DataError(path, f"frames[{fk!r}]: expected an object, got {type(cars).__name__}")
        frames[_int_key(path, "frames", fk)] = {_int_key(path, f"frames[{fk!r}]", k): _seen(path, fk, k, v)
                                                 for k, v in cars.items()}
    return SequenceAttributes(path=path, instances=instances, frames=frames)


def read_attributes(root: str | Path, sequence: int | str) -> SequenceAttributes | None:
    """The sidecar of ``sequence`` under ``root``, or None when there is none."""
    path = attributes_path(root, sequence)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read the attributes sidecar: {exc}") from None
    except json.JSONDecodeError as exc:
        raise DataError(path, f"malformed JSON: {exc}") from None
    return parse_attributes(path, data)
