"""Keep torch's thread count across numba's parallel kernels.

numba's OpenMP threading layer and torch share one OpenMP runtime, and every parallel numba launch sets the
calling thread's OpenMP thread count to numba's (all cores). torch reads that count for its own operators, so
after the first splat a process told ``torch.set_num_threads(1)`` ran XFeat on every core: the count the CLIs
set on purpose (1 unless ``-j``; on a busy 2-core box 2 threads ran XFeat up to 10x slower) held only until the
first render. It also made results depend on the call order: XFeat's keypoints differ in the last bits between
thread counts, so a relocalization database built on a freshly parsed scan (whose render order runs a parallel
numba kernel before torch's first call) differed from one built from the scan cache, feature order and
vocabulary included.

:func:`keeps_torch_threads` wraps a function that starts numba's threads (a parallel kernel, and also
``numba.get_num_threads()``, which starts the pool) and restores the count torch had before the call. It imports
nothing: where torch is not loaded (a client), it does nothing.
"""

from __future__ import annotations

import functools
import sys

__all__ = ["keeps_torch_threads"]


def keeps_torch_threads(fn):
    """``fn``, which runs numba's parallel threads, made to give torch back the thread count it had before."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        torch = sys.modules.get("torch")
        n = torch.get_num_threads() if torch is not None else None
        try:
            return fn(*args, **kwargs)
        finally:
            if n is not None and torch.get_num_threads() != n:
                torch.set_num_threads(n)

    return wrapper
