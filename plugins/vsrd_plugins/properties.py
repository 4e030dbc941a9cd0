"""Reading plugin properties: numbers, lists of numbers, flags and names, with errors that name
the property.

Mitsuba hands a plugin its properties as Python values of a few types: ``str`` (XML, or a
string in ``mi.load_dict``), ``int``, ``float``, ``bool``, a three-component vector (a Python
tuple of three numbers in ``mi.load_dict`` arrives as one) and Dr.Jit arrays (``mi.Float``,
``mi.TensorXf``, ...), which it stores as they are. Mitsuba's own dictionary parser refuses
Python lists (other than three-tuples) and NumPy arrays before any plugin sees them; pass those
through :func:`box_properties`, which turns lists, tuples and NumPy arrays into strings that
both ``mi.load_dict`` and XML accept. The readers here accept every one of these forms.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np


class PropertyError(ValueError):
    """A plugin property has a value of the wrong type, count or range."""


def _where(plugin: str, name: str) -> str:
    return f"{plugin}: property '{name}'"


def _numbers(plugin: str, name: str, value: Any) -> np.ndarray:
    """The numbers of one property value of any accepted form, as a flat float64 array."""
    if isinstance(value, bool):
        return np.array([float(value)])
    if isinstance(value, (int, float, np.integer, np.floating)):
        return np.array([float(value)])
    if isinstance(value, str):
        words = value.replace(",", " ").split()
        try:
            return np.array([float(w) for w in words], dtype=np.float64)
        except ValueError:
            raise PropertyError(f"{_where(plugin, name)}: {value!r} is not a list of numbers") from None
    if isinstance(value, (list, tuple, np.ndarray)):
        try:
            return np.asarray(value, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise PropertyError(f"{_where(plugin, name)}: {value!r} is not a list of numbers") from None
    try:  # Dr.Jit arrays and tensors (scalar vectors included)
        return np.asarray(np.array(value), dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise PropertyError(f"{_where(plugin, name)}: a value of type {type(value).__name__} is not a list "
                            "of numbers") from None


def read_floats(props, plugin: str, name: str, count: int | None = None,
                default: Sequence[float] | float | None = None, minimum: float | None = None,
                positive: bool = False) -> np.ndarray:
    """Property ``name`` as ``count`` finite floats (any count when ``None``).

    ``default`` (a number, repeated, or ``count`` numbers) stands in for a missing property;
    without one a missing property is an error. ``minimum``: every value must be at least this;
    ``positive``: every value must be above 0."""
    if name not in props:
        if default is None:
            raise PropertyError(f"{_where(plugin, name)} is required")
        values = np.broadcast_to(np.asarray(default, dtype=np.float64), (count,) if count is not None else (1,))
        return np.array(values, dtype=np.float64)
    values = _numbers(plugin, name, props[name])
    if count is not None and values.size != count:
        raise PropertyError(f"{_where(plugin, name)} has {values.size} values, expected {count}")
    if not np.all(np.isfinite(values)):
        raise PropertyError(f"{_where(plugin, name)} has non-finite values")
    if positive and np.any(values <= 0.0):
        raise PropertyError(f"{_where(plugin, name)} must be > 0, got {values.min():g}")
    if minimum is not None and np.any(values < minimum):
        raise PropertyError(f"{_where(plugin, name)} must be >= {minimum:g}, got {values.min():g}")
    return values


def read_float(props, plugin: str, name: str, default: float, minimum: float | None = None,
               positive: bool = False) -> float:
    """Property ``name`` as one finite float (``default`` when missing)."""
    return float(read_floats(props, plugin, name, 1, default, minimum, positive)[0])


def read_int(props, plugin: str, name: str, default: int, minimum: int | None = None) -> int:
    """Property ``name`` as one integer, at least ``minimum`` (``default`` when missing)."""
    value = read_float(props, plugin, name, float(default))
    if value != int(value):
        raise PropertyError(f"{_where(plugin, name)} must be an integer, got {value:g}")
    if minimum is not None and value < minimum:
        raise PropertyError(f"{_where(plugin, name)} must be >= {minimum}, got {int(value)}")
    return int(value)


#: Spellings of a flag given as a string (XML and strings in ``mi.load_dict``).
TRUE_WORDS, FALSE_WORDS = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


def read_bool(props, plugin: str, name: str, default: bool) -> bool:
    """Property ``name`` as a flag: a bool, 0 / 1, or one of :data:`TRUE_WORDS` / :data:`FALSE_WORDS`."""
    if name not in props:
        return default
    value = props[name]
    if isinstance(value, str):
        word = value.strip().lower()
        if word in TRUE_WORDS or word in FALSE_WORDS:
            return word in TRUE_WORDS
        raise PropertyError(f"{_where(plugin, name)}: {value!r} is not a flag (true / false)")
    if isinstance(value, (bool, int, np.integer)) and int(value) in (0, 1):
        return bool(value)
    raise PropertyError(f"{_where(plugin, name)}: {value!r} is not a flag (true / false)")


def read_choice(props, plugin: str, name: str, default: str, choices: Sequence[str]) -> str:
    """Property ``name`` as one of the words ``choices``."""
    if name not in props:
        return default
    value = props[name]
    if not isinstance(value, str) or value not in choices:
        raise PropertyError(f"{_where(plugin, name)} must be one of {', '.join(map(repr, choices))}, "
                            f"got {value!r}")
    return value


def format_numbers(values) -> str:
    """Numbers as a space-separated string that reads back to the same float32 values."""
    return " ".join(f"{float(v):.9g}" for v in np.asarray(values, dtype=np.float64).ravel())


def box_properties(centre, size, yaw=None, velocity=None, dynamic=None) -> dict[str, str]:
    """The box properties of ``vsrd_silhouette`` / ``sdf_tracer`` from lists, tuples or NumPy
    arrays, as strings (``mi.load_dict`` and XML ``<string>`` tags accept them).

    Args:
        centre: (N, 3) box centres in the scene frame.
        size: (N, 3) full extents (width, height, length) along the box-local (x, y, z) axes.
        yaw: (N,) yaw angles in radians (length axis along ``(sin yaw, 0, cos yaw)``); None: 0.
        velocity: (N, 3) velocities per unit of ray time, or None for zeros.
        dynamic: (N,) 0/1 flags, or None for all static.
    """
    centre = np.asarray(centre, dtype=np.float64).reshape(-1, 3)
    n = len(centre)

    def shaped(name: str, values, per_box: int) -> np.ndarray:
        values = np.zeros(n * per_box) if values is None else np.asarray(values, dtype=np.float64)
        if values.size != n * per_box:
            raise PropertyError(f"box_properties: '{name}' has {values.size} values, expected {n * per_box} "
                                f"({per_box} per box, {n} boxes)")
        return values.ravel()

    return {"centre": format_numbers(centre), "size": format_numbers(shaped("size", size, 3)),
            "yaw": format_numbers(shaped("yaw", yaw, 1)), "velocity": format_numbers(shaped("velocity", velocity, 3)),
            "dynamic": format_numbers(shaped("dynamic", dynamic, 1))}
