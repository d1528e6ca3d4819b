"""The `?key=value&…` options after a source spec's path (`replay:PATH?…`, `rosbag:PATH?…`), and the
replay options every replay spec shares.

Values are percent-decoded but a `+` stays a `+` (unlike form decoding): a start time's UTC offset
(`start_at=2026-11-28T19:10:00+01:00`) reaches the parser as written. A key may repeat
(`start_signal=file:…&start_signal=udp:…`).
"""

from __future__ import annotations

from urllib.parse import unquote

from camera.sources.clock_sync import ClockSync
from camera.sources.frame import SourceConfigError

#: Options of every replay spec (camera.sources.replay.ReplaySource): the clock sync and the masks switch.
REPLAY_KEYS = ("start_at", "start_signal", "ignore_masks")


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


def replay_options(spec: str, options: list[tuple[str, str]]) -> tuple[ClockSync | None, bool]:
    """(clock sync or None, ignore masks) from a spec's REPLAY_KEYS options (others are the caller's)."""
    start_at = [value for key, value in options if key == "start_at"]
    signals = [value for key, value in options if key == "start_signal"]
    masks = [value for key, value in options if key == "ignore_masks"]
    if len(start_at) > 1 or len(masks) > 1:
        raise SourceConfigError(f"source spec {spec!r}: start_at and ignore_masks may be given once each")
    if masks and masks[0] not in ("true", "false"):
        raise SourceConfigError(f"source spec {spec!r}: ignore_masks is {masks[0]!r}; expected true or false")
    clock_sync = ClockSync.parse(start_at[0] if start_at else None, signals) if start_at or signals else None
    return clock_sync, bool(masks) and masks[0] == "true"
