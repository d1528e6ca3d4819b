"""The `?key=value&…` options after a source spec's path (`replay:PATH?…`, `rosbag:PATH?…`), and the
replay options every replay spec shares.

Values are percent-decoded but a `+` stays a `+` (unlike form decoding): a start time's UTC offset
(`start_at=2026-11-28T19:10:00+01:00`) reaches the parser as written. A key may repeat
(`start_signal=file:…&start_signal=udp:…`).
"""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import unquote

from camera.sources.clock_sync import ClockSync
from camera.sources.frame import SourceConfigError

#: Options of every replay spec (camera.sources.replay.ReplaySource): the clock sync, the masks switch, the late limit.
REPLAY_KEYS = ("start_at", "start_signal", "ignore_masks", "max_late_ms")


@dataclass(frozen=True)
class ReplayOptions:
    """What a replay spec's options ask for (ReplaySource's arguments of the same names)."""

    clock_sync: ClockSync | None = None
    ignore_masks: bool = False
    max_late_ms: float | None = None


def split_spec(spec: str, rest: str, keys: tuple[str, ...]) -> tuple[str, list[tuple[str, str]]]:
    """(path, [(key, value), …]) of what follows `kind:` in `spec`; SourceConfigError for an unknown key
    or an option without `=`."""
    path, _, query = rest.partition("?")
    options = []
    for item in filter(None, query.split("&")):
        key, sep, value = item.partition("=")
        if not sep or key not in keys:
            raise SourceConfigError(
                f"source spec {spec!r}: option {key!r} is unknown; expected KEY=VALUE, KEY one of {', '.join(keys)}"
            )
        options.append((key, unquote(value)))
    return path, options


def replay_options(spec: str, options: list[tuple[str, str]]) -> ReplayOptions:
    """The REPLAY_KEYS options of a spec (others are the caller's); SourceConfigError names a bad one."""
    values = {key: [value for k, value in options if k == key] for key in REPLAY_KEYS}
    if once := [key for key in ("start_at", "ignore_masks", "max_late_ms") if len(values[key]) > 1]:
        raise SourceConfigError(f"source spec {spec!r}: {', '.join(once)} may be given once")
    start_at, signals = values["start_at"], values["start_signal"]
    masks, late = values["ignore_masks"], values["max_late_ms"]
    if masks and masks[0] not in ("true", "false"):
        raise SourceConfigError(f"source spec {spec!r}: ignore_masks is {masks[0]!r}; expected true or false")
    try:
        max_late_ms = float(late[0]) if late else None
    except ValueError:
        max_late_ms = -1.0
    if max_late_ms is not None and not max_late_ms > 0:
        raise SourceConfigError(f"source spec {spec!r}: max_late_ms is {late[0]!r}; expected milliseconds > 0")
    return ReplayOptions(
        ClockSync.parse(start_at[0] if start_at else None, signals) if start_at or signals else None,
        bool(masks) and masks[0] == "true",
        max_late_ms,
    )
