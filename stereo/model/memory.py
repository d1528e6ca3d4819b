"""Giving freed heap memory back to the operating system between the network's stages.

glibc keeps the blocks a stage freed (the 2D backbone's many 10–30 MB activations) in its heaps
instead of unmapping them, where the much larger 3D volumes that follow cannot reuse them: at
384×1248 that is ~0.5 GB of resident memory kept for nothing (measured in benchmarks/RESULTS.md).
`malloc_trim(0)` returns it. It is a glibc extension: on a C library without it (musl, macOS,
Windows) or where no C library can be found, `release_freed_memory` does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's `int malloc_trim(size_t pad)`, or None where the C library has none."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):  # library not loadable / no such symbol
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_freed_memory() -> bool:
    """Return free heap pages to the OS; True when the C library could do it, False (a no-op) elsewhere."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
