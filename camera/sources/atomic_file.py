"""Files that appear whole or not at all: write under a temporary name in the same folder, then rename.

A recording killed (SIGKILL, power cut) in the middle of a write leaves at most a stray
`.NAME.tmp` beside its files, never a truncated file under a name the recording lists: `os.replace`
within one folder is atomic on POSIX filesystems. No fsync: the page cache outlives a killed
process, and a per-file fsync costs more than a frame's budget on SD cards and eMMC (see
camera.sources.recording_format for what a power cut can still lose and how replay reads that).
"""

from __future__ import annotations

import os
from pathlib import Path


def temporary_name(path: Path) -> Path:
    """Where `replace_atomically` writes `path` before renaming it: a hidden `.NAME.tmp` beside it."""
    return path.with_name(f".{path.name}.tmp")


def replace_atomically(path: Path, data: bytes | memoryview) -> None:
    """Write `data` to `path` so that a reader (or a kill) sees the old file, or no file, or all of `data`."""
    temporary = temporary_name(path)
    with temporary.open("wb") as handle:
        handle.write(data)
    os.replace(temporary, path)
