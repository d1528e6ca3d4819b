"""Progress bars that suit where they print: a live tqdm bar on a terminal, sparse plain lines in a log.

On a terminal tqdm redraws one line with carriage returns. Written to a file, a pipe or journald,
every redraw becomes a separate log line (ten a second). `progress_bar` keeps tqdm's bar on a
terminal; elsewhere it prints one plain line (no carriage return, no padding) at most every
`PLAIN_INTERVAL_S` seconds, plus the first and the last state. Used by `record`, `replay`,
`emcstereo synth`, training, evaluation and weight downloads.
"""

from __future__ import annotations

import sys
from typing import Any, TextIO

from tqdm import tqdm

#: Seconds between two plain progress lines when the output is not a terminal.
PLAIN_INTERVAL_S = 30.0


class _PlainLines:
    """A text stream for tqdm that turns each carriage-return redraw into one newline-terminated line."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        line = text.replace("\r", "").rstrip()
        if line:
            self.stream.write(line + "\n")
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


def _is_terminal(stream: TextIO) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # a closed stream
        return False


def progress_bar(
    *,
    desc: str,
    total: int | None = None,
    unit: str = "it",
    disable: bool = False,
    file: TextIO | None = None,
    **options: Any,
) -> tqdm:
    """A tqdm bar on `file` (default stderr): live on a terminal, sparse plain lines otherwise."""
    stream = sys.stderr if file is None else file
    if disable or _is_terminal(stream):
        return tqdm(total=total, desc=desc, unit=unit, disable=disable, file=stream, **options)
    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        file=_PlainLines(stream),
        mininterval=PLAIN_INTERVAL_S,
        maxinterval=PLAIN_INTERVAL_S * 10,
        miniters=1,
        ascii=True,
        dynamic_ncols=False,
        ncols=100,
        **options,
    )
