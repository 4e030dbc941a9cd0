"""vsrd-mi: multi-view 3D box autolabeling (VSRD++) on Mitsuba 3 / Dr.Jit.

Importing the package

1. makes sure Dr.Jit will load a working libLLVM (see :mod:`vsrd_mi._llvm`),
2. selects the Mitsuba variant (``llvm_ad_rgb`` unless ``VSRD_MI_VARIANT`` names another
   ``*_ad_rgb`` variant, e.g. ``cuda_ad_rgb``), and
3. registers the integrators of :mod:`vsrd_plugins` (``vsrd_silhouette``, ``sdf_tracer``) so that
   ``mi.load_dict`` / ``mi.load_file`` find them by name.

Pipeline sub-packages, in order: :mod:`vsrd_mi.data` -> :mod:`vsrd_mi.scene` ->
:mod:`vsrd_mi.render` -> :mod:`vsrd_mi.optimise` -> :mod:`vsrd_mi.export` / :mod:`vsrd_mi.evaluate`.
"""

from __future__ import annotations

import os

from ._llvm import LLVMNotFoundError, ensure_llvm

__version__ = "0.1.0"

DEFAULT_VARIANT = "llvm_ad_rgb"

if not os.environ.get("VSRD_MI_VARIANT", DEFAULT_VARIANT).startswith("cuda"):
    ensure_llvm()

import mitsuba as mi  # noqa: E402  (must come after ensure_llvm)

VARIANT = os.environ.get("VSRD_MI_VARIANT", DEFAULT_VARIANT)
if mi.variant() is None or not mi.variant().endswith("_ad_rgb"):
    mi.set_variant(VARIANT)

import vsrd_plugins  # noqa: E402

vsrd_plugins.register()

__all__ = ["LLVMNotFoundError", "ensure_llvm", "VARIANT", "__version__"]
