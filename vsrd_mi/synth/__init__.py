"""Synthetic KITTI-360 sequences (the generator, apart from the readers in :mod:`vsrd_mi.data`).

:func:`generate_sequence` lays out a street (:mod:`.layout`: the world of :mod:`.world`, parked
rows of :mod:`.parking`, props of :mod:`.props`), builds the cars (:mod:`.cars`: mesh files and
the basic procedural cars; :mod:`.vehicles`: eight procedural vehicle classes), ray-casts both
rectified cameras with Mitsuba (:mod:`.render`, textures in :mod:`.texture`), writes the
KITTI-360 release layout and the per-car attributes file (:mod:`.attributes`). Every setting is
a field of :class:`SynthConfig` (:mod:`.config`); :mod:`.suites` holds the development and
validation sets; ``vsrd-mi synth`` is :mod:`.cli`, ``vsrd-mi synth-suite`` :mod:`.suite_cli`.
Design notes: ``docs/synthetic.md``.
"""

from .config import SynthConfig
from .generate import (
           SynthSummary,
           generate_sequence,
           render_frame,
           write_annotations,
           write_png,
)

__all__ = ["SynthConfig", "SynthSummary", "generate_sequence", "render_frame", "write_annotations",
           "write_png"]
