"""Reading one autopilot parameter by name over MAVLink: PARAM_REQUEST_READ, answered by PARAM_VALUE.

A request or its answer can be lost on a radio or a busy serial link, so a read is sent again after
`PARAM_READ_TIMEOUT_S` without an answer, `PARAM_READ_ATTEMPTS` times in all; an autopilot that
has no such parameter does not answer at all (ArduPilot and PX4 alike), which reads as None.

PARAM_VALUE carries every value in a float field. ArduPilot casts integers to float; PX4 copies an
integer's bytes into the float's (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE), so its integer
parameters are decoded from the bytes by their `param_type`.
"""

from __future__ import annotations

import struct
import time
from typing import Any

PARAM_READ_TIMEOUT_S = 0.5
PARAM_READ_ATTEMPTS = 3
#: MAV_PARAM_TYPE → the struct format of an integer held bytewise in the first bytes of the float.
BYTEWISE_FORMATS = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}


def decode_param_value(msg: Any, bytewise: bool) -> float:
    """The value of a PARAM_VALUE `msg`: an integer type decoded from the float's bytes when `bytewise` (PX4)."""
    value = float(msg.param_value)
    layout = BYTEWISE_FORMATS.get(int(msg.param_type)) if bytewise else None
    if layout is None:
        return value
    raw = struct.pack("<f", value)
    return float(struct.unpack(layout, raw[: struct.calcsize(layout)])[0])


def read_parameter(
    conn: Any,
    target: tuple[int, int],
    name: str,
    *,
    bytewise: bool,
    timeout_s: float = PARAM_READ_TIMEOUT_S,
    attempts: int = PARAM_READ_ATTEMPTS,
) -> float | None:
    """The value of parameter `name` of the autopilot `target` (system, component) on the pymavlink
    connection `conn`; None when no answer came after `attempts` requests `timeout_s` apart."""
    for _ in range(attempts):
        conn.mav.param_request_read_send(target[0], target[1], name.encode("ascii"), -1)
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=left)
            if msg is not None and msg.param_id == name and msg.get_srcSystem() == target[0]:
                return decode_param_value(msg, bytewise)
    return None
