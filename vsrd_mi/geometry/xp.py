"""Array namespaces letting one formula run on NumPy (data, evaluation) and Dr.Jit (optimisation).

Each namespace provides ``where(cond, a, b)``, ``minimum``, ``maximum``, ``abs`` and ``sqrt``.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

NP = SimpleNamespace(where=np.where, minimum=np.minimum, maximum=np.maximum, abs=np.abs, sqrt=np.sqrt)


def drjit_namespace() -> SimpleNamespace:
    """The Dr.Jit namespace (imported lazily so NumPy users never import Dr.Jit)."""
    import drjit as dr
    return SimpleNamespace(where=dr.select, minimum=dr.minimum, maximum=dr.maximum, abs=dr.abs,
                           sqrt=dr.safe_sqrt)
