"""Keeping an external simulator or autopilot in step with a replay: a start time and a start signal.

A replay schedules frame i at `start + (t_i − t_0)`. An outside program that must stay in step
(a flight simulator, a SITL autopilot fed the same sequence) needs `start`: the replay can wait
until a wall-clock instant agreed beforehand (`start_at`), and/or announce the instant it started
(`start_signal`): a JSON object written to a file (atomically: a reader polling the path never
sees half of it) and/or sent as one UDP datagram. The object (schema `branchrange/replay-start/v1`):

    {"schema": "branchrange/replay-start/v1", "source": "…", "wall_ns": …, "monotonic_ns": …,
     "first_timestamp_ns": …, "first_index": …}

`wall_ns` is the Unix time (ns) at which the first frame was released, `monotonic_ns` the same
instant on this computer's monotonic clock, `first_timestamp_ns`/`first_index` that frame's
recorded stamp and index: frame k is released at `wall_ns + (timestamp_k − first_timestamp_ns)`.

Text forms (command line and source specs): a signal is `file:PATH` or `udp:HOST:PORT` (IPv6 as
`udp:[::1]:PORT`); a start time is Unix seconds (`1764353400.5`) or ISO 8601 with a UTC offset
(`2026-11-28T18:10:00Z`, `2026-11-28T19:10:00+01:00`).
"""

from __future__ import annotations

import json
import logging
import os
import socket
import tempfile
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from camera.sources.frame import SourceConfigError

log = logging.getLogger("camera.sources.clock_sync")

START_SCHEMA = "branchrange/replay-start/v1"
SIGNAL_FORMS = "file:PATH or udp:HOST:PORT"


@dataclass(frozen=True)
class StartSignal:
    """Where the start instant is announced: a file (`path`) or a UDP address (`address`, resolved)."""

    text: str
    path: Path | None = None
    address: tuple[str, int] | None = None


@dataclass(frozen=True)
class StartInstant:
    """When a replay released its first frame: Unix and monotonic ns, and that frame's recorded stamp and index."""

    source: str
    wall_ns: int
    monotonic_ns: int
    first_timestamp_ns: int
    first_index: int

    def to_json(self) -> str:
        """The `branchrange/replay-start/v1` object (see the module docstring) as one line of JSON."""
        return json.dumps(
            {
                "schema": START_SCHEMA,
                "source": self.source,
                "wall_ns": self.wall_ns,
                "monotonic_ns": self.monotonic_ns,
                "first_timestamp_ns": self.first_timestamp_ns,
                "first_index": self.first_index,
            }
        )


def parse_start_signal(text: str) -> StartSignal:
    """A signal from `file:PATH` (its folder must exist) or `udp:HOST:PORT` (HOST resolved now, so a typo
    fails before the replay starts). Raises SourceConfigError naming the value and the expected form."""
    kind, _, rest = text.partition(":")
    if kind == "file" and rest:
        path = Path(rest)
        if not path.parent.is_dir():
            raise SourceConfigError(
                f"start signal {text!r}: the folder {path.parent} does not exist; expected a file in an existing folder"
            )
        return StartSignal(text, path=path)
    if kind == "udp":
        host, sep, port_text = rest.rpartition(":")
        host = host.removeprefix("[").removesuffix("]")
        if sep and host and port_text.isdigit() and 0 < int(port_text) < 65536:
            try:
                *_, sockaddr = socket.getaddrinfo(host, int(port_text), type=socket.SOCK_DGRAM)[0]
            except (socket.gaierror, UnicodeError) as error:
                raise SourceConfigError(f"start signal {text!r}: host {host!r} is unknown ({error})") from error
            return StartSignal(text, address=(str(sockaddr[0]), int(sockaddr[1])))
    raise SourceConfigError(f"start signal {text!r}: expected {SIGNAL_FORMS} (e.g. udp:127.0.0.1:9500)")


def parse_start_at(text: str) -> float:
    """Unix seconds of a start time given as Unix seconds or ISO 8601 with a UTC offset (see the module docstring).

    A time without an offset is refused: on a companion computer set to UTC and a laptop that is
    not, it would name two different instants."""
    try:
        return float(text)
    except ValueError:
        pass
    try:
        instant = datetime.fromisoformat(text)
    except ValueError:
        instant = None
    if instant is None or instant.tzinfo is None:
        raise SourceConfigError(
            f"start time {text!r}: expected Unix seconds (e.g. 1764353400) or ISO 8601 with a UTC offset "
            "(e.g. 2026-11-28T18:10:00Z or 2026-11-28T19:10:00+01:00)"
        )
    return instant.timestamp()


@dataclass(frozen=True)
class ClockSync:
    """A replay's start: wait until `start_at_s` (Unix seconds; None: start at once), then announce the
    start instant on every one of `signals`."""

    start_at_s: float | None = None
    signals: tuple[StartSignal, ...] = ()

    @classmethod
    def parse(cls, start_at: str | None, signals: list[str] | tuple[str, ...] = ()) -> ClockSync:
        """From their text forms (see the module docstring); SourceConfigError for a bad one."""
        return cls(
            None if start_at is None else parse_start_at(start_at), tuple(parse_start_signal(s) for s in signals)
        )

    def wait_for_start(self, stop: threading.Event) -> None:
        """Block until `start_at_s` on the wall clock (or `stop` is set); a start time already past is logged."""
        if self.start_at_s is None:
            return
        late_s = time.time() - self.start_at_s
        if late_s > 0:
            log.warning("start time %.3f passed %.3f s ago: starting now", self.start_at_s, late_s)
            return
        log.info("waiting %.3f s for the start time %.3f (Unix seconds)", -late_s, self.start_at_s)
        while not stop.is_set() and (remaining := self.start_at_s - time.time()) > 0:
            stop.wait(remaining)  # re-checked on the wall clock: an NTP step during the wait is followed

    def announce(self, start: StartInstant) -> None:
        """Log the start instant and send it to every signal; a signal that fails is logged, the replay goes on."""
        line = start.to_json()
        log.info("replay started: %s", line)
        for signal in self.signals:
            try:
                if signal.path is not None:
                    _write_atomically(signal.path, line + "\n")
                elif signal.address is not None:
                    _send_datagram(signal.address, line.encode("utf-8"))
            except OSError as error:
                log.error("start signal %s could not be sent: %s", signal.text, error)


def _write_atomically(path: Path, text: str) -> None:
    """`text` into `path` through a temporary file in the same folder and a rename."""
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write(text)
        os.replace(temporary, path)
    except OSError:
        Path(temporary).unlink(missing_ok=True)
        raise


def _send_datagram(address: tuple[str, int], payload: bytes) -> None:
    """One UDP datagram to `address` (IPv4 or IPv6)."""
    family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as sock:
        sock.sendto(payload, address)
