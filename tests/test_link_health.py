"""Link health tells the truth: connected only while the autopilot's HEARTBEAT arrives (real UDP, signing)."""

from __future__ import annotations

import logging
import socket
import time

import pytest
from autopilot_sim import MAV_AUTOPILOT_INVALID, MAV_TYPE_GCS, AutopilotSim, approach_flight

from branchrange.config.sections import MavlinkConfig
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay, connection

KEY = bytes(range(32))
HOVER = approach_flight(0.0)


def relay_to(port: int, **overrides) -> MavlinkRelay:
    return MavlinkRelay(MavlinkConfig(url=f"udpout:127.0.0.1:{port}", **overrides), CameraMount.from_rpy())


def wait_for(predicate, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "signing.key"
    path.write_bytes(KEY)
    return path


def test_nothing_listening_is_not_connected_although_the_socket_is_open():
    with relay_to(free_udp_port()) as relay:
        time.sleep(0.6)  # a heartbeat and a few frame sets went out into the void
        state = relay.link_state()
    assert state["transport_open"] is True and state["sent"] > 0
    assert state["connected"] is False and state["peer"] is None and state["received"] == 0
    assert state["peer_heartbeat_age_s"] is None and state["mode"] == "camera"


def test_autopilot_connects_within_two_heartbeats_and_names_its_ids():
    with AutopilotSim(HOVER, heartbeat_period_s=0.2) as sim, relay_to(sim.port) as relay:
        assert wait_for(lambda: relay.link_state()["connected"], 2.0)
        beats_needed = sim.heartbeats_sent
        state = relay.link_state()
    assert beats_needed <= 2
    assert state["peer"]["system_id"] == 1 and state["peer"]["component_id"] == 1
    assert state["peer"]["autopilot"] == 3 and state["peer"]["armed"] is True and state["peer"]["custom_mode"] == 4
    assert state["peer_heartbeat_age_s"] < 0.3 and state["received"] >= 1 and state["signature_failures"] == 0


class _Heartbeat:
    """An autopilot's HEARTBEAT (system 1, component 1) as pymavlink hands it over."""

    type, autopilot, base_mode, custom_mode = 2, 3, 0, 4

    def get_type(self) -> str:
        return "HEARTBEAT"

    def get_srcSystem(self) -> int:  # noqa: N802 - pymavlink's name
        return 1

    def get_srcComponent(self) -> int:  # noqa: N802 - pymavlink's name
        return 1


class _OneHeartbeatConnection:
    """Delivers one HEARTBEAT, then, at the poll's next read, takes the link's state as another thread (the
    API's) may take it in between: on one busy core it said connected with 0 received."""

    def __init__(self) -> None:
        self.link: connection.MavlinkLink | None = None
        self.states: list[dict] = []
        self._delivered = False

    def recv_msg(self) -> _Heartbeat | None:
        if self._delivered:
            assert self.link is not None
            self.states.append(self.link.state())
            return None
        self._delivered = True
        return _Heartbeat()

    def close(self) -> None:
        pass


def test_the_link_state_never_says_connected_with_nothing_received(monkeypatch):
    fake = _OneHeartbeatConnection()
    monkeypatch.setattr(connection, "open_connection", lambda url, **options: fake)
    link = connection.MavlinkLink("udpout:127.0.0.1:9")
    fake.link = link
    assert len(link.poll()) == 1
    (during,) = fake.states
    assert during["connected"] is True and during["received"] == 1
    assert link.state()["received"] == 1  # counted once


def test_a_ground_station_heartbeat_is_not_the_autopilot():
    with (
        AutopilotSim(HOVER, heartbeat_period_s=0.1, mav_type=MAV_TYPE_GCS, autopilot=MAV_AUTOPILOT_INVALID) as sim,
        relay_to(sim.port) as relay,
    ):
        assert wait_for(lambda: sim.heartbeats_sent >= 4, 2.0)
        time.sleep(0.1)
        state = relay.link_state()
    assert state["received"] >= 3 and state["connected"] is False and state["peer"] is None


def test_heartbeats_that_stop_mean_lost_after_three_seconds():
    with AutopilotSim(HOVER, heartbeat_period_s=0.1) as sim, relay_to(sim.port) as relay:
        assert wait_for(lambda: relay.link_state()["connected"], 2.0)
        sim.heartbeats_on = False
        stopped = time.monotonic()
        time.sleep(2.5)
        still_up = relay.link_state()["connected"]  # 3 s timeout (the MAVLink convention, the default)
        assert wait_for(lambda: not relay.link_state()["connected"], 1.0)
        lost_after = time.monotonic() - stopped
    assert still_up is True
    assert 2.9 <= lost_after <= 3.5, lost_after  # the last beat left up to one period (0.1 s) before `stopped`


def test_a_peer_with_the_wrong_signing_key_is_never_connected(key_file):
    with (
        AutopilotSim(HOVER, heartbeat_period_s=0.1, signing_key=bytes(32)) as sim,
        relay_to(sim.port, signing_key_file=str(key_file)) as relay,
    ):
        assert wait_for(lambda: sim.heartbeats_sent >= 5, 2.0)
        time.sleep(0.1)
        state = relay.link_state()
    assert state["connected"] is False and state["peer"] is None and state["received"] == 0
    assert state["signature_failures"] >= 4


def test_a_wrong_key_is_said_once_per_episode_with_its_count_not_once_per_message(key_file, caplog, monkeypatch):
    monkeypatch.setattr(connection, "SIGNATURE_EPISODE_GAP_S", 0.5)
    caplog.set_level(logging.INFO)
    with AutopilotSim(HOVER, heartbeat_period_s=0.02, signing_key=bytes(32)) as sim:
        with relay_to(sim.port, signing_key_file=str(key_file)) as relay:
            assert wait_for(lambda: relay.link_state()["signature_failures"] >= 20, 3.0)
            sim.close()  # the wrong key stops: the episode ends after a calm gap
            texts = lambda: [r.getMessage() for r in caplog.records]  # noqa: E731
            assert wait_for(lambda: any("with a wrong signature dropped" in t for t in texts()), 3.0)
            failures = relay.link_state()["signature_failures"]
    assert not any("sig mismatch" in t for t in texts())  # pymavlink's line per message is gone
    began = [t for t in texts() if "wrong signature arrive" in t]
    summed = [t for t in texts() if "with a wrong signature dropped" in t]
    assert len(began) == 1 and len(summed) == 1
    assert int(summed[0].split(": ")[1].split()[0]) == failures >= 20


def test_an_unsigned_peer_is_not_connected_to_a_signed_relay_but_a_signed_one_is(key_file):
    with (
        AutopilotSim(HOVER, heartbeat_period_s=0.1) as sim,
        relay_to(sim.port, signing_key_file=str(key_file)) as relay,
    ):
        assert wait_for(lambda: sim.heartbeats_sent >= 4, 2.0)
        time.sleep(0.1)
        unsigned = relay.link_state()
    with (
        AutopilotSim(HOVER, heartbeat_period_s=0.1, signing_key=KEY) as sim,
        relay_to(sim.port, signing_key_file=str(key_file)) as relay,
    ):
        assert wait_for(lambda: relay.link_state()["connected"], 2.0)
        signed = relay.link_state()
    assert unsigned["connected"] is False and unsigned["signature_failures"] >= 3
    assert signed["signature_failures"] == 0 and signed["signing"] is True


class RelayLive:
    """The daemon as the API sees it, reduced to its relay (the part /health and /metrics report)."""

    def __init__(self, relay: MavlinkRelay):
        self.relay = relay

    def latest_result(self):
        return None

    def health(self):
        return {"camera": {"source": "zed:/dev/zedmini:HD720", "lost": False}, "mavlink": self.relay.link_state()}


def test_health_hides_source_and_url_without_the_token_and_metrics_report_the_link():
    from fastapi.testclient import TestClient

    from api import create_app
    from branchrange.config.sections import ApiConfig

    with AutopilotSim(HOVER, heartbeat_period_s=0.1) as sim, relay_to(sim.port) as relay:
        assert wait_for(lambda: relay.link_state()["connected"], 2.0)
        with TestClient(create_app(ApiConfig(token="t0ken"), None, state=RelayLive(relay))) as client:
            anonymous = client.get("/health").json()
            wrong = client.get("/health", headers={"Authorization": "Bearer nope"}).json()
            crew = client.get("/health", headers={"Authorization": "Bearer t0ken"}).json()
            metrics = client.get("/metrics", headers={"Authorization": "Bearer t0ken"}).text
        url = f"udpout:127.0.0.1:{sim.port}"
    for body in (anonymous, wrong):
        assert "source" not in body["camera"] and "url" not in body["mavlink"]
        assert (
            body["status"] == "ok"
            and body["mavlink"]["connected"] is True
            and body["mavlink"]["peer"]["system_id"] == 1
        )
    assert crew["camera"]["source"] == "zed:/dev/zedmini:HD720" and crew["mavlink"]["url"] == url
    lines = dict(line.rsplit(" ", 1) for line in metrics.splitlines() if line.startswith("branchrange_mavlink_"))
    assert lines['branchrange_mavlink_connected{system_id="1",component_id="1"}'] == "1"
    assert float(lines["branchrange_mavlink_heartbeat_age_seconds"]) < 0.5
    assert int(lines["branchrange_mavlink_messages_received_total"]) >= 1
    assert int(lines["branchrange_mavlink_signature_failures_total"]) == 0
