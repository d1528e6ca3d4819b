"""The MAVLink link checks: the autopilot's HEARTBEAT, its type, signing, and its parameters.

BranchRange opens the link as the daemon would (`mavlink.url`, `baud`, its system and component id,
the signing key), says HEARTBEAT itself every `OUR_HEARTBEAT_PERIOD_S` (a UDP autopilot listening with
`udpin` learns where to answer from it), and waits up to `mavlink.heartbeat_timeout_s` for the
autopilot's. The HEARTBEAT's `autopilot` field picks the parameter table
(`autopilot_parameters`); each parameter is then read by name (`parameter_read`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from branchrange.onboard.mavlink.connection import (
    MAV_AUTOPILOT_INVALID,
    PeerHeartbeat,
    SigningKeyError,
    autopilot_heartbeat,
    load_signing_key,
    open_connection,
)
from branchrange.onboard.preflight.autopilot_parameters import (
    AUTOPILOT_NAMES,
    MAV_AUTOPILOT_PX4,
    ParameterRule,
    rules_for,
)
from branchrange.onboard.preflight.parameter_read import read_parameter
from branchrange.onboard.preflight.report import CheckResult

if TYPE_CHECKING:
    from branchrange.config.sections import MavlinkConfig

OUR_HEARTBEAT_PERIOD_S = 0.5
MAV_TYPE_ONBOARD_CONTROLLER, MAV_STATE_ACTIVE = 18, 4
HEARTBEAT, AUTOPILOT, SIGNING = "autopilot heartbeat", "autopilot type", "MAVLink signing"


@dataclass(frozen=True)
class HeardHeartbeat:
    """What listening for the autopilot's HEARTBEAT gave: the beat (None when none came) and the signature
    counts of everything received meanwhile (pymavlink's: signed, verified, wrong)."""

    beat: PeerHeartbeat | None
    signed: int
    good_signatures: int
    bad_signatures: int


def listen_for_heartbeat(conn: Any, timeout_s: float) -> HeardHeartbeat:
    """Send our HEARTBEAT and read until the autopilot's arrives or `timeout_s` passes."""
    deadline = time.monotonic() + timeout_s
    next_beat = 0.0
    beat = None
    while beat is None and (now := time.monotonic()) < deadline:
        if now >= next_beat:
            conn.mav.heartbeat_send(MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)
            next_beat = now + OUR_HEARTBEAT_PERIOD_S
        msg = conn.recv_match(blocking=True, timeout=min(0.05, max(0.0, deadline - now)))
        if msg is not None and msg.get_type() != "BAD_DATA":
            beat = autopilot_heartbeat(msg, time.monotonic())
    signing = conn.mav.signing
    return HeardHeartbeat(beat, signing.sig_count, signing.goodsig_count, signing.badsig_count)


def check_autopilot(mavlink: MavlinkConfig) -> list[CheckResult]:
    """The link checks in order: heartbeat, autopilot type, signing, then one check per required parameter."""
    if not mavlink.enabled:
        return [CheckResult.skipped(HEARTBEAT, "mavlink.enabled is false: BranchRange sends nothing")]
    try:
        key = load_signing_key(mavlink.signing_key_file) if mavlink.signing_key_file else None
    except SigningKeyError as exc:
        return [CheckResult.failed(SIGNING, str(exc), "point mavlink.signing_key_file at the autopilot's 32-byte key")]
    try:
        conn = open_connection(
            mavlink.url,
            baud=mavlink.baud,
            source_system=mavlink.system_id,
            source_component=mavlink.component_id,
            signing_key=key,
        )
    except (OSError, ValueError) as exc:
        return [
            CheckResult.failed(
                HEARTBEAT,
                f"cannot open {mavlink.url}: {exc}",
                "set mavlink.url to the autopilot's port (a serial device that exists, or udpout:/tcp:HOST:PORT)",
            )
        ]
    try:
        heard = listen_for_heartbeat(conn, mavlink.heartbeat_timeout_s)
        results = [_heartbeat_result(mavlink, heard), _autopilot_result(heard.beat), _signing_result(key, heard)]
        if heard.beat is not None:
            rules = rules_for(heard.beat.autopilot, mavlink)
            target = (heard.beat.system_id, heard.beat.component_id)
            bytewise = heard.beat.autopilot == MAV_AUTOPILOT_PX4
            for rule in rules or ():
                results.append(_parameter_result(rule, read_parameter(conn, target, rule.name, bytewise=bytewise)))
        return results
    finally:
        conn.close()


def _heartbeat_result(mavlink: MavlinkConfig, heard: HeardHeartbeat) -> CheckResult:
    beat = heard.beat
    if beat is not None:
        state = "armed" if beat.armed else "disarmed"
        return CheckResult.passed(
            HEARTBEAT, f"system {beat.system_id}, component {beat.component_id}, {state}, on {mavlink.url}"
        )
    found = f"no HEARTBEAT from an autopilot on {mavlink.url} within {mavlink.heartbeat_timeout_s:g} s"
    if heard.bad_signatures:
        found += f" ({heard.bad_signatures} message(s) with a wrong signature dropped)"
    return CheckResult.failed(
        HEARTBEAT,
        found,
        "power the autopilot and check mavlink.url, the wiring, the autopilot's serial port protocol "
        f"(ArduPilot SERIALn_PROTOCOL = 2) and its baud rate = mavlink.baud ({mavlink.baud})",
    )


def _autopilot_result(beat: PeerHeartbeat | None) -> CheckResult:
    if beat is None:
        return CheckResult.skipped(AUTOPILOT, "no HEARTBEAT to read it from")
    name = AUTOPILOT_NAMES.get(beat.autopilot)
    if name is not None:
        return CheckResult.passed(AUTOPILOT, f"{name} (MAV_AUTOPILOT {beat.autopilot}), vehicle type {beat.mav_type}")
    return CheckResult.failed(
        AUTOPILOT,
        f"MAV_AUTOPILOT {beat.autopilot}, for which BranchRange has no parameter table",
        "fly ArduPilot (Copter ≥ 4.3) or PX4 (≥ 1.14); otherwise check its avoidance settings by hand",
    )


def _signing_result(key: bytes | None, heard: HeardHeartbeat) -> CheckResult:
    if heard.beat is None and not (heard.signed or heard.bad_signatures):
        return CheckResult.skipped(SIGNING, "nothing received from the autopilot")
    if key is not None and heard.bad_signatures:
        return CheckResult.failed(
            SIGNING,
            f"{heard.bad_signatures} message(s) signed with another key (or not signed), {heard.good_signatures} "
            "with mavlink.signing_key_file's key",
            "load the same signing key on the autopilot and in mavlink.signing_key_file",
        )
    if key is not None:
        return CheckResult.passed(SIGNING, f"on: {heard.good_signatures} message(s) verified with the key")
    if heard.signed:
        return CheckResult.failed(
            SIGNING,
            f"the autopilot signs its messages ({heard.signed} signed) but BranchRange has no key: "
            "the autopilot drops what BranchRange sends unsigned",
            "set mavlink.signing_key_file to the autopilot's signing key",
        )
    return CheckResult.passed(SIGNING, "off on both sides")


def _parameter_result(rule: ParameterRule, value: float | None) -> CheckResult:
    name = f"parameter {rule.name}"
    if value is None:
        return CheckResult.failed(
            name,
            "the autopilot did not answer PARAM_REQUEST_READ for it (no such parameter in this firmware?)",
            f"update the firmware to one that has {rule.name}, then set {rule.name} = {rule.wanted} ({rule.why})",
        )
    if rule.accepts(value):
        return CheckResult.passed(name, f"{value:g}")
    return CheckResult.failed(
        name, f"{value:g}", f"set {rule.name} = {rule.wanted} ({rule.why}), write it and reboot the autopilot"
    )
