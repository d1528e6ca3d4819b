"""The link under the relay: MAVLink 2 signing, TCP peers that go away and come back, serial ports."""

from __future__ import annotations

import math
import os
import select
import time

import pytest
from mavlink_peer import LoopbackPeer, of_type
from result_factory import branch, frame_result

from branchrange.config.sections import MavlinkConfig, TrackingConfig
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay
from branchrange.onboard.mavlink.connection import SigningKeyError, load_signing_key, mavutil_v2

KEY = bytes(range(32))
RESULT = frame_result([branch(4, [0.0, 0.0, 1.2])], target_id=4)


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "signing.key"
    path.write_bytes(KEY)
    return path


def signed_relay(peer: LoopbackPeer, key_file) -> MavlinkRelay:
    cfg = MavlinkConfig(url=f"udpout:127.0.0.1:{peer.port}", signing_key_file=str(key_file))
    return MavlinkRelay(cfg, CameraMount.from_rpy())


def test_peer_with_the_signing_key_accepts_signed_messages(key_file):
    peer = LoopbackPeer(signing_key=KEY)
    try:
        with signed_relay(peer, key_file) as relay:
            relay.publish(RESULT)
            got = peer.collect(1.0, until=lambda r: bool(of_type(r, "DEBUG_VECT")))
            assert relay.link_state()["signing"] is True
    finally:
        peer.close()
    assert of_type(got, "HEARTBEAT") and of_type(got, "DISTANCE_SENSOR")
    signing = peer.conn.mav.signing
    assert signing.goodsig_count == len(got) and signing.badsig_count == 0 and not peer.bad


def test_peer_with_another_key_rejects_every_message(key_file):
    peer = LoopbackPeer(signing_key=bytes(32))
    try:
        with signed_relay(peer, key_file) as relay:
            relay.publish(RESULT)
            got = peer.collect(0.6)
    finally:
        peer.close()
    assert got == []
    assert peer.conn.mav.signing.badsig_count > 0 and peer.bad
    assert "signature" in str(peer.bad[0].reason).lower()


def test_peer_that_requires_signing_rejects_an_unsigned_relay():
    peer = LoopbackPeer(signing_key=KEY)
    try:
        cfg = MavlinkConfig(url=f"udpout:127.0.0.1:{peer.port}")
        with MavlinkRelay(cfg, CameraMount.from_rpy()) as relay:
            relay.publish(RESULT)
            got = peer.collect(0.6)
    finally:
        peer.close()
    assert got == [] and peer.bad and peer.conn.mav.signing.goodsig_count == 0


def test_signing_key_file_takes_raw_bytes_or_hex_and_names_a_bad_file(tmp_path, key_file):
    assert load_signing_key(key_file) == KEY
    hex_file = tmp_path / "hex.key"
    hex_file.write_text(KEY.hex() + "\n")
    assert load_signing_key(hex_file) == KEY
    short = tmp_path / "short.key"
    short.write_bytes(b"too short")
    with pytest.raises(SigningKeyError, match="short.key.*32-byte"):
        load_signing_key(short)
    with pytest.raises(SigningKeyError, match="missing.key"):
        load_signing_key(tmp_path / "missing.key")


def test_relay_keeps_working_after_the_tcp_peer_goes_away_and_comes_back():
    peer = LoopbackPeer(url="tcpin:127.0.0.1:0")
    port = peer.port
    # results stay fresh for 2 s: a loaded machine's slow reconnect must not turn this into a staleness test
    cfg = MavlinkConfig(url=f"tcp:127.0.0.1:{port}", reconnect_interval_s=0.2, send_rate_hz=10.0, max_result_age_s=2.0)
    with MavlinkRelay(cfg, CameraMount.from_rpy()) as relay:
        relay.publish(RESULT)
        assert of_type(peer.collect(1.0, until=lambda r: bool(of_type(r, "DISTANCE_SENSOR"))), "DISTANCE_SENSOR")
        peer.close()  # the flight controller goes away
        deadline = time.monotonic() + 3.0
        while relay.link_state()["transport_open"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert relay.link_state()["transport_open"] is False and relay.link_state()["connected"] is False
        relay.publish(RESULT)  # the pipeline goes on; nothing raises
        peer = LoopbackPeer(url=f"tcpin:127.0.0.1:{port}")  # and comes back on the same port
        try:
            relay.publish(RESULT)
            got = peer.collect(3.0, until=lambda r: bool(of_type(r, "DISTANCE_SENSOR")))
        finally:
            peer.close()
        state = relay.link_state()
    assert of_type(got, "DISTANCE_SENSOR")[-1].msg.current_distance == 120
    assert state["reconnects"] >= 1 and state["send_errors"] >= 1


def test_relay_speaks_over_a_serial_port():
    master, slave = os.openpty()
    try:
        cfg = MavlinkConfig(url=os.ttyname(slave), baud=57600)
        parser = mavutil_v2().mavlink.MAVLink(None)
        got = []
        with MavlinkRelay(cfg, CameraMount.from_rpy()) as relay:
            for _ in range(TrackingConfig().target_min_observations):  # a target needs results in a row
                relay.publish(RESULT)
            deadline = time.monotonic() + 2.0
            # until the published target's set is complete (DEBUG_VECT is its last message); sets sent
            # before `publish` say "no target" (NaN)
            while time.monotonic() < deadline and not any(
                m.get_type() == "DEBUG_VECT" and not math.isnan(m.x) for m in got
            ):
                if select.select([master], [], [], 0.05)[0]:
                    got += parser.parse_buffer(os.read(master, 4096)) or []
    finally:
        os.close(master)
        os.close(slave)
    types = {m.get_type() for m in got}
    assert {"HEARTBEAT", "DISTANCE_SENSOR", "OBSTACLE_DISTANCE_3D", "DEBUG_VECT"} <= types
    assert 120 in [m.current_distance for m in got if m.get_type() == "DISTANCE_SENSOR"]
