"""Optional compiled kernels: a numba module where numba is installed, else None and the caller's numpy path.

The light client (P&L on a headset or robot) must run from the base install, which has no numba; where numba is
there (the workstation and server installs, ``pip install .[site]``), the hot loops of P&L tracking run compiled
instead: the same arithmetic, a window or a point at a time, several times faster. ``CRISTAL_KERNELS=numpy`` turns
them off (to compare, or to reproduce a light client's numbers on a workstation).
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType

__all__ = ["optional_kernels", "ENV"]

ENV = "CRISTAL_KERNELS"
_loaded: dict[str, ModuleType | None] = {}


def optional_kernels(module: str) -> ModuleType | None:
    """The kernel module ``module`` (imported once), or None where numba is missing or ``CRISTAL_KERNELS=numpy``."""
    if os.environ.get(ENV, "").lower() == "numpy":
        return None
    if module not in _loaded:
        try:
            _loaded[module] = importlib.import_module(module)
        except ImportError:  # numba not installed: the caller's numpy path
            _loaded[module] = None
    return _loaded[module]
