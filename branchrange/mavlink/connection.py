"""The MAVLink 2 link to the flight controller: open, send, read, and reopen after errors.

pymavlink picks its wire protocol from the environment variable `MAVLINK20` at the moment a
dialect is selected (`mavutil.set_dialect` reads it), and every connection object encodes with the
dialect module current when it was created. `mavutil_v2()` is the one place in BranchRange that
sets both (MAVLink 2, ardupilotmega, needed for OBSTACLE_DISTANCE_3D and signing); everything
else gets pymavlink through it. The variable is process-wide: other pymavlink users in the same
process also speak MAVLink 2 afterwards, which is what a MAVLink 2 system wants.

`MavlinkLink` never raises into its caller once constructed: a failed open or a send/read error
marks the link down, and the next `send`/`poll` after `reconnect_interval_s` opens a fresh
connection (TCP peers that went away and came back, serial adapters unplugged and replugged).
It is not thread-safe: one thread owns it (the relay's).
"""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from types import ModuleType
from typing import Any

DIALECT = "ardupilotmega"
SIGNING_KEY_BYTES = 32


class SigningKeyError(ValueError):
    """A signing key file that is missing or does not hold a 32-byte key."""


def mavutil_v2() -> ModuleType:
    """pymavlink's `mavutil`, switched to MAVLink 2 with the ardupilotmega dialect."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    if mavutil.current_dialect != DIALECT or mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        mavutil.set_dialect(DIALECT)
    return mavutil


def load_signing_key(path: str | Path) -> bytes:
    """The 32-byte MAVLink 2 signing key in `path`: 32 raw bytes, or 64 hex digits as text."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SigningKeyError(f"{path}: cannot read the signing key ({exc.strerror})") from None
    if len(data) == SIGNING_KEY_BYTES:
        return data
    text = data.strip()
    if len(text) == 2 * SIGNING_KEY_BYTES:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningKeyError(f"{path}: expected a 32-byte signing key (32 raw bytes or 64 hex digits), "
                          f"found {len(data)} bytes")


def open_connection(url: str, *, baud: int = 115200, source_system: int = 1,
                    source_component: int = 191, signing_key: bytes | None = None) -> Any:
    """A pymavlink MAVLink 2 connection for `url` (udpout:/udpin:/tcp:HOST:PORT or a serial path).

    Raises OSError/ValueError when it cannot be opened. TCP connects once (no blocking retries)
    and reports a dead peer as an exception on the next write, so `MavlinkLink` can reopen it.
    Signed links sign what they send and accept only correctly signed messages.
    """
    mavutil = mavutil_v2()
    conn = mavutil.mavlink_connection(
        url, baud=baud, source_system=source_system, source_component=source_component,
        dialect=DIALECT, autoreconnect=url.startswith("tcp:"), retries=0)
    if signing_key is not None:
        conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=None, link_id=0)
    return conn


class MavlinkLink:
    """A connection that reopens itself: `send` and `poll` report failure, never raise."""

    def __init__(self, url: str, *, baud: int = 115200, source_system: int = 1,
                 source_component: int = 191, signing_key: bytes | None = None,
                 reconnect_interval_s: float = 1.0, clock: Callable[[], float] = time.monotonic):
        self.url = url
        self._open_args = dict(baud=baud, source_system=source_system,
                               source_component=source_component, signing_key=signing_key)
        self._signing = signing_key is not None
        self._reconnect_interval_s = reconnect_interval_s
        self._clock = clock
        self._conn: Any = None
        self._next_attempt = 0.0
        self._opens = 0
        self.last_error: str | None = None
        self.sent = 0
        self.send_errors = 0
        self.received = 0
        self._peer_heartbeat_at: float | None = None
        self._ensure_open()

    @property
    def connected(self) -> bool:
        """Whether a connection is open (for UDP: the socket; the peer may still be absent)."""
        return self._conn is not None

    def _ensure_open(self) -> bool:
        """Open the connection if it is closed and the reconnect interval has passed."""
        if self._conn is not None:
            return True
        now = self._clock()
        if now < self._next_attempt:
            return False
        self._next_attempt = now + self._reconnect_interval_s
        try:
            self._conn = open_connection(self.url, **self._open_args)
        except (OSError, ValueError) as exc:
            self.last_error = f"open {self.url}: {exc}"
            return False
        self._opens += 1
        return True

    def _drop(self, exc: BaseException) -> None:
        """Close a failed connection; the next send/poll after the interval reopens it."""
        self.last_error = f"{type(exc).__name__}: {exc}"
        conn, self._conn = self._conn, None
        self._next_attempt = self._clock() + self._reconnect_interval_s
        try:
            conn.close()
        except Exception:  # noqa: BLE001 - a half-dead socket may fail to close; it is gone either way
            pass

    def send(self, messages: Iterable[Any]) -> bool:
        """Send messages back to back; False (and the link marked down) when the link failed."""
        if not self._ensure_open():
            self.send_errors += 1
            return False
        try:
            for msg in messages:
                self._conn.mav.send(msg)
                self.sent += 1
            if getattr(self._conn, "portdead", False):  # pymavlink's serial write swallows errors
                raise OSError(f"serial device {self.url} stopped accepting writes")
        except Exception as exc:  # noqa: BLE001 - any transport failure: drop and reopen later
            self.send_errors += 1
            self._drop(exc)
            return False
        return True

    def poll(self, max_messages: int = 200) -> list[Any]:
        """Read what the peer has sent (non-blocking), noting its heartbeats; [] when down."""
        if not self._ensure_open():
            return []
        received = []
        try:
            for _ in range(max_messages):
                msg = self._conn.recv_msg()
                if msg is None:
                    break
                if msg.get_type() == "BAD_DATA":
                    continue
                received.append(msg)
                if msg.get_type() == "HEARTBEAT":
                    self._peer_heartbeat_at = self._clock()
        except Exception as exc:  # noqa: BLE001 - a read error means the link is gone
            self._drop(exc)
        self.received += len(received)
        return received

    def state(self) -> dict[str, Any]:
        """Link facts for /health and the status line (plain JSON types)."""
        age = None if self._peer_heartbeat_at is None else round(self._clock() - self._peer_heartbeat_at, 3)
        return {"url": self.url, "connected": self.connected, "signing": self._signing,
                "reconnects": max(0, self._opens - 1), "sent": self.sent,
                "send_errors": self.send_errors, "received": self.received,
                "peer_heartbeat_age_s": age, "last_error": self.last_error}

    def close(self) -> None:
        """Close the connection for good (no reopening after this)."""
        if self._conn is not None:
            conn, self._conn = self._conn, None
            conn.close()
        self._next_attempt = float("inf")
