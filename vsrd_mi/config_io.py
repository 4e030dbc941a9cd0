"""Configuration dataclasses rebuilt from their dict (or JSON) form.

``dataclasses.asdict`` turns nested configuration groups into dicts and JSON turns tuples into
lists; :func:`dataclass_from_dict` undoes both, so a configuration survives the round trip a batch
task's fingerprint and a saved box file make.
"""

from __future__ import annotations

import dataclasses
from typing import TypeVar

T = TypeVar("T")


def dataclass_from_dict(cls: type[T], d: dict) -> T:
    """``cls`` built from a dict of (some of) its fields: a dict given for a field whose default
    is a dataclass becomes that dataclass (recursively), a list given for a tuple field a tuple;
    missing fields keep their defaults, an unknown key raises TypeError."""
    defaults = cls()
    kwargs = {}
    for key, value in d.items():
        default = getattr(defaults, key, None)
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = dataclass_from_dict(type(default), value)
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        kwargs[key] = value
    return cls(**kwargs)
