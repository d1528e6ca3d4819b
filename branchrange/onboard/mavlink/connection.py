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

An open socket says nothing about the flight controller (a UDP socket opens with nobody
listening), so the link is *connected* only while HEARTBEATs of an autopilot arrive: the first
HEARTBEAT whose `autopilot` is not MAV_AUTOPILOT_INVALID and whose type is not a GCS or an
onboard computer names the peer (system and component id), and the link is lost
`heartbeat_timeout_s` after its newest one. With signing on, pymavlink drops unsigned and
wrong-key messages before they are decoded, so they never count as the peer; they are counted as
signature failures. pymavlink also logs each one at INFO ("sig mismatch", ~60 lines a second from an
autopilot signing with another key): those lines are filtered out, and the link says it once per
episode instead — a warning when the first arrives, and the count when none came for
`SIGNATURE_EPISODE_GAP_S`.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

DIALECT = "ardupilotmega"
SIGNING_KEY_BYTES = 32
#: pymavlink's INFO lines for one rejected signature each (wrong key, replayed or too old a timestamp).
PYMAVLINK_SIGNING_NOISE = frozenset({"sig mismatch", "old timestamp", "bad new stream %s %s"})
#: An episode of signature failures ends when none arrived for this long (s); its count is logged then.
SIGNATURE_EPISODE_GAP_S = 5.0

log = logging.getLogger("branchrange.mavlink")


class _SigningNoise(logging.Filter):
    """Drops pymavlink's per-message signature lines (`MavlinkLink` counts them and says so per episode)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.msg not in PYMAVLINK_SIGNING_NOISE


class SigningKeyError(ValueError):
    """A signing key file that is missing or does not hold a 32-byte key."""


def mavutil_v2() -> ModuleType:
    """pymavlink's `mavutil`, switched to MAVLink 2 with the ardupilotmega dialect."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    if mavutil.current_dialect != DIALECT or mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        mavutil.set_dialect(DIALECT)
    dialect_log = logging.getLogger(mavutil.mavlink.__name__)
    if not any(isinstance(f, _SigningNoise) for f in dialect_log.filters):
        dialect_log.addFilter(_SigningNoise())
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
    raise SigningKeyError(
        f"{path}: expected a 32-byte signing key (32 raw bytes or 64 hex digits), found {len(data)} bytes"
    )


def open_connection(
    url: str,
    *,
    baud: int = 115200,
    source_system: int = 1,
    source_component: int = 191,
    signing_key: bytes | None = None,
) -> Any:
    """A pymavlink MAVLink 2 connection for `url` (udpout:/udpin:/tcp:HOST:PORT or a serial path).

    Raises OSError/ValueError when it cannot be opened. TCP connects once (no blocking retries)
    and reports a dead peer as an exception on the next write, so `MavlinkLink` can reopen it.
    Signed links sign what they send and accept only correctly signed messages.
    """
    mavutil = mavutil_v2()
    conn = mavutil.mavlink_connection(
        url,
        baud=baud,
        source_system=source_system,
        source_component=source_component,
        dialect=DIALECT,
        autoreconnect=url.startswith("tcp:"),
        retries=0,
    )
    if signing_key is not None:
        conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=None, link_id=0)
    return conn


#: HEARTBEAT types that are never the flight controller (MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER).
NOT_AUTOPILOT_TYPES = frozenset({6, 18})
MAV_AUTOPILOT_INVALID = 8
MAV_MODE_FLAG_SAFETY_ARMED = 128


@dataclass(frozen=True)
class PeerHeartbeat:
    """The autopilot's newest HEARTBEAT: who sent it, its mode, and when it arrived (our clock, s)."""

    system_id: int
    component_id: int
    mav_type: int
    autopilot: int
    base_mode: int
    custom_mode: int
    at: float

    @property
    def armed(self) -> bool:
        """Whether the autopilot reports its motors armed."""
        return bool(self.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON view for /health."""
        return {
            "system_id": self.system_id,
            "component_id": self.component_id,
            "type": self.mav_type,
            "autopilot": self.autopilot,
            "custom_mode": self.custom_mode,
            "armed": self.armed,
        }


def autopilot_heartbeat(msg: Any, at: float) -> PeerHeartbeat | None:
    """A `PeerHeartbeat` when `msg` is a flight controller's HEARTBEAT, else None."""
    if msg.get_type() != "HEARTBEAT" or msg.autopilot == MAV_AUTOPILOT_INVALID or msg.type in NOT_AUTOPILOT_TYPES:
        return None
    return PeerHeartbeat(
        msg.get_srcSystem(), msg.get_srcComponent(), msg.type, msg.autopilot, msg.base_mode, msg.custom_mode, at
    )


class MavlinkLink:
    """A connection that reopens itself: `send` and `poll` report failure, never raise."""

    def __init__(
        self,
        url: str,
        *,
        baud: int = 115200,
        source_system: int = 1,
        source_component: int = 191,
        signing_key: bytes | None = None,
        reconnect_interval_s: float = 1.0,
        heartbeat_timeout_s: float = 3.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.url = url
        self._open_args = dict(
            baud=baud, source_system=source_system, source_component=source_component, signing_key=signing_key
        )
        self._signing = signing_key is not None
        self._reconnect_interval_s = reconnect_interval_s
        self._heartbeat_timeout_s = heartbeat_timeout_s
        self._clock = clock
        self._conn: Any = None
        self._next_attempt = 0.0
        self._opens = 0
        self.last_error: str | None = None
        self.sent = 0
        self.send_errors = 0
        self.received = 0
        self.signature_failures = 0
        self._episode: tuple[float, float, int] | None = None  # signature failures: first, newest (s), count
        self.peer: PeerHeartbeat | None = None
        self._ensure_open()

    @property
    def transport_open(self) -> bool:
        """Whether the socket/port is open (for UDP this says nothing about a peer)."""
        return self._conn is not None

    @property
    def connected(self) -> bool:
        """Whether the autopilot's HEARTBEAT arrived within `heartbeat_timeout_s`."""
        return self.peer is not None and self._clock() - self.peer.at <= self._heartbeat_timeout_s

    def from_peer(self, msg: Any) -> bool:
        """Whether `msg` was sent by the connected autopilot (its system and component id)."""
        return (
            self.connected
            and msg.get_srcSystem() == self.peer.system_id
            and msg.get_srcComponent() == self.peer.component_id
        )

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
        """Read what arrived (non-blocking), noting the autopilot's heartbeats; [] when down. Each message is
        counted before its heartbeat is noted: `state()`, read from another thread, never says connected with
        nothing received (it did between the two on a starved CPU)."""
        if not self._ensure_open():
            return []
        received, bad_signatures = [], 0
        try:
            for _ in range(max_messages):
                msg = self._conn.recv_msg()
                if msg is None:
                    break
                if msg.get_type() == "BAD_DATA":
                    bad_signatures += "signature" in str(getattr(msg, "reason", "")).lower()
                    continue
                received.append(msg)
                self.received += 1
                self._note_heartbeat(msg)
        except Exception as exc:  # noqa: BLE001 - a read error means the link is gone
            self._drop(exc)
        self.signature_failures += bad_signatures
        self._signature_episode(bad_signatures, self._clock())
        return received

    def _signature_episode(self, failures: int, now: float) -> None:
        """Say that wrongly signed messages arrive once when they begin, and how many when they stop."""
        if failures:
            if self._episode is None:
                log.warning(
                    "MAVLink %s: messages with a wrong signature arrive (the autopilot signs with another key, "
                    "or not at all) and are dropped; their count follows when they stop",
                    self.url,
                )
            first = now if self._episode is None else self._episode[0]
            self._episode = (first, now, failures + (0 if self._episode is None else self._episode[2]))
        elif self._episode is not None and now - self._episode[1] >= SIGNATURE_EPISODE_GAP_S:
            self._end_signature_episode()

    def _end_signature_episode(self) -> None:
        if self._episode is not None:
            first, newest, count = self._episode
            log.warning(
                "MAVLink %s: %d message(s) with a wrong signature dropped over %.1f s", self.url, count, newest - first
            )
            self._episode = None

    def _note_heartbeat(self, msg: Any) -> None:
        """Take an autopilot HEARTBEAT from the current peer, or from a new one once the old is lost."""
        beat = autopilot_heartbeat(msg, self._clock())
        if beat is None:
            return
        same = self.peer is not None and (beat.system_id, beat.component_id) == (
            self.peer.system_id,
            self.peer.component_id,
        )
        if same or not self.connected:
            self.peer = beat

    def state(self) -> dict[str, Any]:
        """Link facts for /health and the status line (plain JSON types)."""
        age = None if self.peer is None else round(self._clock() - self.peer.at, 3)
        return {
            "url": self.url,
            "connected": self.connected,
            "transport_open": self.transport_open,
            "signing": self._signing,
            "peer": None if self.peer is None else self.peer.to_dict(),
            "reconnects": max(0, self._opens - 1),
            "sent": self.sent,
            "send_errors": self.send_errors,
            "received": self.received,
            "signature_failures": self.signature_failures,
            "peer_heartbeat_age_s": age,
            "last_error": self.last_error,
        }

    def close(self) -> None:
        """Close the connection for good (no reopening after this); an episode of bad signatures is summed up."""
        self._end_signature_episode()
        if self._conn is not None:
            conn, self._conn = self._conn, None
            conn.close()
        self._next_attempt = float("inf")
