"""A loopback MAVLink 2 peer standing in for the flight controller: it decodes what was really sent."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from branchrange.onboard.mavlink.connection import mavutil_v2


@dataclass
class Received:
    """One decoded message and the monotonic time (s) it arrived."""

    msg: Any
    at: float

    @property
    def type(self) -> str:
        return self.msg.get_type()


@dataclass
class LoopbackPeer:
    """A pymavlink connection (`udpin:127.0.0.1:0` by default) that collects decoded messages."""

    url: str = "udpin:127.0.0.1:0"
    signing_key: bytes | None = None
    received: list[Received] = field(default_factory=list)
    bad: list[Any] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.conn = mavutil_v2().mavlink_connection(self.url, source_system=1, source_component=1)
        if self.signing_key is not None:
            self.conn.setup_signing(self.signing_key, sign_outgoing=False, allow_unsigned_callback=None)

    @property
    def port(self) -> int:
        """The port the peer listens on (the OS picks it for port 0)."""
        sock = getattr(self.conn, "listen", None) or self.conn.port
        return sock.getsockname()[1]

    def collect(self, seconds: float, until: Any = None) -> list[Received]:
        """Read for up to `seconds` or until `until(received so far)` is true (checked every 20 ms)."""
        start = len(self.received)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            msg = self.conn.recv_match(blocking=True, timeout=0.02)
            if msg is not None and msg.get_type() == "BAD_DATA":
                self.bad.append(msg)
            elif msg is not None:
                self.received.append(Received(msg, time.monotonic()))
            if until is not None and until(self.received[start:]):
                break
        return self.received[start:]

    def close(self) -> None:
        self.conn.close()


def of_type(received: list[Received], name: str) -> list[Received]:
    """The received messages of one MAVLink type, in arrival order."""
    return [r for r in received if r.type == name]
