"""The daemon's JSONL results log, rotated by size so hours in the field cannot fill the disk.

About 56 MB an hour at the onboard rate: past `max_bytes` the file becomes `NAME.1` (the older
ones `NAME.2` … `NAME.KEEP`, the oldest deleted) and a new `NAME` starts with the run's header
line again, so every file reads on its own (`frame_results.read_runs`; a file that starts with
the same header as the one before it continues that run). Rotation happens between lines: files
hold whole lines only. Not `logging.handlers.RotatingFileHandler`: it has no hook to start each new
file with a header, and the lines are data, not log records (no levels, formatting or filters).

Two faults of the field are handled here, because the log must never stop the vehicle's sensor:
- a full disk (or any write error): the line is dropped, whatever part of it reached the file is cut
  off again (the file keeps whole lines only), and writing resumes by itself with the first line that
  fits. One error is logged for the episode, and one info line when writing works again: a nearly full
  filesystem takes a short line into a block it already gave the file and refuses the next, so writes
  may come and go for a while — within `ERROR_REPEAT_S` of the error that is the same episode, silent;
- a daemon killed in the middle of a line (SIGKILL, power loss) leaves a torn last line without its
  newline: the next run ends it with a newline and says so in its header (`"previous_line_torn": true`),
  so the header is never glued to the fragment and a reader knows that line is not a result.
"""

from __future__ import annotations

import io
import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger("branchrange.daemon")
#: The run header's key saying the line before it is a fragment left by a run that was killed mid-line.
TORN_KEY = "previous_line_torn"
#: Seconds after a logged write error within which further errors are the same episode (not logged again).
ERROR_REPEAT_S = 60.0


class ResultsLog:
    """Appends lines to `path` (created with its folder), rotating past `max_bytes` (0: never), keeping `keep`
    older files; each file starts with `header`, written when this log opens (a run's first line)."""

    def __init__(
        self,
        path: str | Path,
        header: str,
        *,
        max_bytes: int = 0,
        keep: int = 1,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if max_bytes < 0 or keep < 1:
            raise ValueError(f"max_bytes is {max_bytes} and keep {keep}; expected max_bytes ≥ 0 and keep ≥ 1")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.header, self.max_bytes, self.keep = header, max_bytes, keep
        self.rotations = 0
        self.dropped_lines = 0  # lines lost to write errors (a full disk), over the run
        self._failing = False  # the last write failed
        self._clock = clock
        self._error_logged_at = -ERROR_REPEAT_S  # when the newest write error was logged (clock s)
        self._resume_logged = True  # the episode's "writing again" is logged (or there was none)
        self._file = self._open()
        torn = self._size > 0 and self._last_byte() != b"\n"
        if torn:  # a run killed mid-line: end the fragment so the header gets a line of its own
            self._append("\n")
        # a restart appends to the same log: each run starts with its header
        self._append(json.dumps({**json.loads(header), TORN_KEY: True}) + "\n" if torn else header)
        self.warn_if_it_can_fill_the_disk()

    def warn_if_it_can_fill_the_disk(self) -> None:
        """Log a warning when the log and its rotated files may grow past the space its filesystem has left:
        `max_bytes` × (`keep` + 1) against the free space plus what the files hold already. A full disk does not
        stop the daemon (lines are dropped), but the newest results are then lost, and the disk is full for
        whatever else needs it. (Without rotation, `max_bytes` 0, the size is the user's choice: not warned.)"""
        if not self.max_bytes:
            return
        files = (self.path, *map(self._numbered, range(1, self.keep + 1)))
        held = sum(p.stat().st_size for p in files if p.exists())
        try:
            room = shutil.disk_usage(self.path.parent).free + held
        except OSError:  # not a filesystem that says: nothing to compare
            return
        if self.max_bytes * (self.keep + 1) > room:
            log.warning(
                "results log %s can grow to %.0f MiB (results_max_mb × (results_keep + 1)) on a filesystem with "
                "%.0f MiB left for it: it can fill the disk (lower [log] results_max_mb or results_keep)",
                self.path,
                self.max_bytes * (self.keep + 1) / 2**20,
                room / 2**20,
            )

    def _open(self) -> io.FileIO:
        """The log file, unbuffered: each line is one write, or cut off again; `_size` from the file."""
        file = self.path.open("ab", buffering=0)
        self._size = os.fstat(file.fileno()).st_size
        return file

    def _last_byte(self) -> bytes:
        with self.path.open("rb") as file:
            file.seek(self._size - 1)
            return file.read(1)

    def write(self, line: str) -> None:
        """Append one line (newline included), rotating first when it would take the file past `max_bytes` —
        unless the file holds nothing but its header (a line longer than the limit still gets a file)."""
        if self.max_bytes and self._size + _bytes(line) > self.max_bytes and self._size > _bytes(self.header):
            try:
                self._rotate()
            except OSError as error:
                self._failed(error)
                return
        self._append(line)

    def _append(self, line: str) -> None:
        """Write `line` whole, or drop it (a write error: see the module docstring); never raises."""
        data = line.encode("utf-8")
        try:
            written = 0
            while written < len(data):
                written += self._file.write(data[written:])
        except OSError as error:
            self._cut_back()
            self._failed(error)
            return
        self._size += len(data)
        self._failing = False
        if not self._resume_logged:
            self._resume_logged = True
            log.info("results log %s: writing again after %d dropped lines", self.path, self.dropped_lines)

    def _cut_back(self) -> None:
        """Remove a partly written line, so the file ends on a whole line (freeing space needs no space)."""
        try:
            os.ftruncate(self._file.fileno(), self._size)
        except OSError:  # not a regular file (e.g. /dev/full): nothing was kept there to cut
            pass

    def _failed(self, error: OSError) -> None:
        self.dropped_lines += 1
        now = self._clock()
        if not self._failing and now - self._error_logged_at >= ERROR_REPEAT_S:
            self._error_logged_at, self._resume_logged = now, False
            log.error(
                "results log %s: cannot write (%s); results are not logged until it can, MAVLink and the API go on",
                self.path,
                error.strerror or error,
            )
        self._failing = True

    def _rotate(self) -> None:
        """NAME → NAME.1 → … → NAME.KEEP (the oldest dropped), then a fresh NAME that starts with the header."""
        for older in range(self.keep - 1, 0, -1):
            moved = self._numbered(older)
            if moved.exists():
                moved.replace(self._numbered(older + 1))
        self.path.replace(self._numbered(1))  # the open file moves with its name
        self.rotations += 1
        size = self._size
        try:
            fresh = self._open()
        except OSError:
            self._size = size  # no new file (no inode left): go on in NAME.1 and say why
            raise
        self._file.close()
        self._file = fresh
        self._append(self.header)

    def _numbered(self, number: int) -> Path:
        return self.path.with_name(f"{self.path.name}.{number}")

    def close(self) -> None:
        """Close the file; idempotent."""
        self._file.close()


def _bytes(line: str) -> int:
    """The size of `line` in the file (UTF-8), bytes."""
    return len(line.encode("utf-8"))
