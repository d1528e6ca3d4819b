"""Giving freed heap memory back to the operating system between the network's stages.

glibc keeps the blocks a stage freed (the 2D backbone's many 10–30 MB activations) in its heaps
instead of unmapping them, where the much larger 3D volumes that follow cannot reuse them: at
384×1248 that is ~0.5 GB of resident memory kept for nothing (measured in benchmarks/RESULTS.md).
`malloc_trim(0)` returns it. On a C library without `malloc_trim` this does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _malloc_trim() -> ctypes._CFuncPtr | None:
    """glibc's `malloc_trim`, or None where the C library has none (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None


def release_freed_memory() -> bool:
    """Return free heap pages to the OS; True when the C library could do it."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
