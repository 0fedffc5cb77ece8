"""Keep freed memory in the process: a training step then reuses its pages instead of faulting.

A training step allocates and frees the same large tensors (activations, gradients) every
step. With glibc's defaults much of that freed memory is given back to the kernel, and the
next step takes new pages, each a page fault: tens to hundreds per step, about 5 % of the
default training's time on a 2-core machine (docs/training.md, "Data split, batches,
epochs, threads"). :func:`keep_freed_memory` sets glibc's thresholds so that freed memory stays
with the process for reuse. The arithmetic is untouched: the same weights, bit for bit.

It changes the whole process for good (as ``MALLOC_*`` environment variables would), so
only the commands that train call it, not the library's functions.
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["MMAP_THRESHOLD", "TOP_PAD", "TRIM_THRESHOLD", "keep_freed_memory"]

#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
#: Blocks below this come from the heap, not from ``mmap`` (glibc's largest: 32 MiB).
MMAP_THRESHOLD = 32 << 20
#: Free memory at the top of a heap is given back only above this much.
TRIM_THRESHOLD = 1 << 30
#: Extra memory taken whenever a heap grows, so that it grows less often.
TOP_PAD = 64 << 20


def keep_freed_memory() -> bool:
    """Set glibc's allocator to keep freed memory (module docstring); False where not glibc.

    Returns
    -------
    bool
        True when all three thresholds were set; False on a C library without ``mallopt``
        (musl, macOS, Windows), where nothing is changed.
    """
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    settings = (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
        (_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
        (_M_TOP_PAD, TOP_PAD),
    )
    return all(mallopt(param, value) == 1 for param, value in settings)
