"""Synthetic KITTI-360 sequences (the generator, apart from the readers in :mod:`vsrd_mi.data`).

:func:`generate_sequence` lays out a street (:mod:`.world`), builds the cars (:mod:`.cars`),
ray-casts both rectified cameras with Mitsuba (:mod:`.render`, textures in :mod:`.texture`) and
writes the KITTI-360 release layout; every setting is a field of :class:`SynthConfig`
(:mod:`.config`); ``vsrd-mi synth`` is :mod:`.cli`.
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
