"""A process whose wall clock can be jumped while the machine's is left alone (the soak's and a test's
clock faults; issue 39).

libfaketime (the `libfaketime` package of the dev extra ships its shared library) is preloaded into a
child process: every wall-clock read of that process — `time.time`, `datetime.now`, the C library's
`clock_gettime(CLOCK_REALTIME)` that logging, uvicorn's Date header and pymavlink's signing read —
is the real time plus the offset written in a file, read again at every wall-clock read. The
monotonic clocks are not faked (`FAKETIME_DONT_FAKE_MONOTONIC`): they are what the daemon must
measure every age and latency with, and what is judged. Other engineers on the machine, and the
soak itself, keep the real clock.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

#: Where the package keeps the shared library, under its own folder.
LIBRARY = Path("vendor") / "libfaketime" / "src" / "libfaketime.so.1"


def library() -> Path | None:
    """The libfaketime shared library, None when the package is not installed."""
    spec = importlib.util.find_spec("libfaketime")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / LIBRARY
    return path if path.is_file() else None


def set_offset(offset_file: Path, seconds: float) -> None:
    """Make the wall clock of the shimmed processes read `seconds` ahead of the real one (negative: behind).
    Written to a temporary name and renamed, so a reader never sees half a line."""
    partial = offset_file.with_name(offset_file.name + ".tmp")
    partial.write_text(f"{seconds:+.0f}\n", encoding="ascii")
    partial.replace(offset_file)


def shim_env(offset_file: Path) -> dict[str, str]:
    """Environment variables that start a child process under the shim, its offset read from `offset_file`
    (set to 0 here when it does not exist). Raises RuntimeError when libfaketime is not installed."""
    lib = library()
    if lib is None:
        raise RuntimeError("libfaketime is not installed: `make setup` installs it (the dev extra)")
    if not offset_file.exists():
        set_offset(offset_file, 0)
    return {
        "LD_PRELOAD": str(lib),
        "FAKETIME_TIMESTAMP_FILE": str(offset_file),
        "FAKETIME_DONT_FAKE_MONOTONIC": "1",
        "FAKETIME_DONT_RESET": "1",
        # without this, a timed wait on a monotonic condition variable (CPython's GIL hand-over) is computed
        # from the real wall time and stalls threads for up to seconds at a jump: an artefact of the shim
        "FAKETIME_FORCE_MONOTONIC_FIX": "0",
        "FAKETIME_NO_CACHE": "1",  # the offset file read at each wall-clock read (~8 µs): a jump is at once
    }
