"""The daemon's JSONL results log, rotated by size so hours in the field cannot fill the disk.

About 56 MB an hour at the onboard rate: past `max_bytes` the file becomes `NAME.1` (the older
ones `NAME.2` … `NAME.KEEP`, the oldest deleted) and a new `NAME` starts with the run's header
line again, so every file reads on its own (`frame_results.read_runs`; a file that starts with
the same header as the one before it continues that run). Rotation happens between lines: files
hold whole lines only. Not `logging.handlers.RotatingFileHandler`: it has no hook to start each new
file with a header, and the lines are data, not log records (no levels, formatting or filters).
"""

from __future__ import annotations

from pathlib import Path


class ResultsLog:
    """Appends lines to `path` (created with its folder), rotating past `max_bytes` (0: never), keeping `keep`
    older files; each file starts with `header`, written when this log opens (a run's first line)."""

    def __init__(self, path: str | Path, header: str, *, max_bytes: int = 0, keep: int = 1) -> None:
        if max_bytes < 0 or keep < 1:
            raise ValueError(f"max_bytes is {max_bytes} and keep {keep}; expected max_bytes ≥ 0 and keep ≥ 1")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.header, self.max_bytes, self.keep = header, max_bytes, keep
        self.rotations = 0
        self._file = self.path.open("a", encoding="utf-8", buffering=1)  # one flushed line per frame
        self._size = self.path.stat().st_size
        self._append(header)  # a restart appends to the same log: each run starts with its header

    def write(self, line: str) -> None:
        """Append one line (newline included), rotating first when it would take the file past `max_bytes` —
        unless the file holds nothing but its header (a line longer than the limit still gets a file)."""
        if self.max_bytes and self._size + _bytes(line) > self.max_bytes and self._size > _bytes(self.header):
            self._rotate()
        self._append(line)

    def _append(self, line: str) -> None:
        self._file.write(line)
        self._size += _bytes(line)

    def _rotate(self) -> None:
        """NAME → NAME.1 → … → NAME.KEEP (the oldest dropped), then a fresh NAME that starts with the header."""
        self._file.close()
        for older in range(self.keep - 1, 0, -1):
            moved = self._numbered(older)
            if moved.exists():
                moved.replace(self._numbered(older + 1))
        self.path.replace(self._numbered(1))
        self.rotations += 1
        self._file = self.path.open("a", encoding="utf-8", buffering=1)
        self._size = 0
        self._append(self.header)

    def _numbered(self, number: int) -> Path:
        return self.path.with_name(f"{self.path.name}.{number}")

    def close(self) -> None:
        """Close the file; idempotent."""
        self._file.close()


def _bytes(line: str) -> int:
    """The size of `line` in the file (UTF-8), bytes."""
    return len(line.encode("utf-8"))
