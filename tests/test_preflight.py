"""`branchrange preflight` against a replayed camera and the loopback autopilot: a passing run, and each fault
the field team must not arm with caught with its fix."""

from __future__ import annotations

import json
import shutil
import socket
import time
from pathlib import Path

import pytest
from api_scene import BASELINE_M, FOCAL_PX, bar_scene
from autopilot_sim import MAV_AUTOPILOT_PX4, AutopilotSim, approach_flight

from branchrange.cli import main as branchrange_main
from branchrange.commands.exit_codes import BAD_INPUT, CHECK_FAILED, DONE
from branchrange.config.sections import MavlinkConfig
from branchrange.core.segmentation.learned import SHIPPED_MODELS
from branchrange.onboard.mavlink.connection import open_connection
from branchrange.onboard.preflight.autopilot_parameters import ardupilot_rules
from branchrange.onboard.preflight.camera_checks import SAMPLED_FRAMES, read_frames
from branchrange.onboard.preflight.parameter_read import read_parameter
from camera.calibration import from_rectified
from camera.opencv_file import write_opencv_file
from camera.sources import FaultInjectingSource, FaultPlan, Recorder, ReplaySource, StereoFrame

FRAMES, PERIOD_NS = 6, 100_000_000  # 10 fps: four frames are read in 0.3 s
WIDTH, HEIGHT = 320, 256
ARDUPILOT_PARAMETERS = ["PRX1_TYPE", "AVOID_ENABLE", "AVOID_MARGIN", "SYSID_THISMAV"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Six frames of the bar scene at 10 fps with its rectified calibration."""
    scene = bar_scene(WIDTH, HEIGHT)
    out = tmp_path_factory.mktemp("rec") / "bar"
    calibration = from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (WIDTH, HEIGHT))
    with Recorder(out, calibration=calibration, source_spec="synthetic bar") as recorder:
        for i in range(FRAMES):
            recorder.write(StereoFrame(scene.left, scene.right, 1_000_000_000 + i * PERIOD_NS, i))
    return out


@pytest.fixture
def autopilot():
    """The loopback autopilot as a correctly set up ArduPilot copter."""
    with AutopilotSim(approach_flight(0.0), heartbeat_period_s=0.1, poll_s=0.005) as sim:
        yield sim


def write_config(tmp_path: Path, source: str, port: int, extra: str = "") -> Path:
    """A daemon configuration: `source`, sgbm at max_disp 64, the link to the autopilot on `port`; the latency
    budget is 5 s, as the test machine's two cores are shared (the learned segmenter alone takes ~0.4 s here)."""
    config = tmp_path / "drone.toml"
    config.write_text(
        f'[camera]\nsource = "{source}"\n[stereo]\nmax_disp = 64\n'
        f'[mavlink]\nurl = "udpout:127.0.0.1:{port}"\nheartbeat_timeout_s = 2.0\nmax_result_age_s = 5.0\n{extra}'
    )
    return config


def with_calibration(config: Path, calibration: Path) -> Path:
    """`config` with camera.calibration set to `calibration`."""
    config.write_text(config.read_text().replace("[camera]\n", f'[camera]\ncalibration = "{calibration}"\n', 1))
    return config


def preflight(capsys, config: Path, *args: str) -> tuple[int, dict]:
    """Exit code and the `--json` report of `branchrange preflight --config config args…`."""
    code = branchrange_main(["preflight", "--config", str(config), "--json", *args])
    return code, json.loads(capsys.readouterr().out)


def by_name(report: dict) -> dict[str, dict]:
    return {check["name"]: check for check in report["checks"]}


def failed(report: dict) -> dict[str, dict]:
    return {check["name"]: check for check in report["checks"] if check["status"] == "fail"}


def test_preflight_with_a_replay_camera_passes_against_the_loopback_autopilot(recording, autopilot, tmp_path, capsys):
    code, report = preflight(capsys, write_config(tmp_path, f"replay:{recording}", autopilot.port))
    checks = by_name(report)
    assert code == DONE and report["ready"] and report["failed"] == 0, report
    assert all(check["status"] == "pass" and check["fix"] == "" for check in report["checks"]), report
    assert set(checks) >= {"camera", "calibration", "models", "pipeline latency", "autopilot heartbeat"}
    assert "configured 10 fps" in checks["camera"]["found"]
    assert "ArduPilot" in checks["autopilot type"]["found"]
    assert [name.removeprefix("parameter ") for name in checks if name.startswith("parameter ")] == ARDUPILOT_PARAMETERS
    assert checks["parameter PRX1_TYPE"]["found"] == "2" and checks["parameter AVOID_MARGIN"]["found"] == "1"
    reads = [r.msg.param_id for r in autopilot.of_type("PARAM_REQUEST_READ")]
    assert reads == ARDUPILOT_PARAMETERS  # each answered at the first request


def test_a_missing_camera_is_caught_with_its_fix(autopilot, tmp_path, capsys):
    code, report = preflight(capsys, write_config(tmp_path, f"replay:{tmp_path / 'no-such-recording'}", autopilot.port))
    assert code == CHECK_FAILED and not report["ready"]
    assert set(failed(report)) == {"camera"}
    assert "no-such-recording" in failed(report)["camera"]["found"]
    assert "plug the camera in" in failed(report)["camera"]["fix"]
    assert [by_name(report)[name]["status"] for name in ("calibration", "pipeline latency")] == ["skip", "skip"]


def test_frames_slower_than_the_configured_rate_are_caught(autopilot, tmp_path, capsys):
    """A recording at 10 fps (its median period) whose first frames came 0.8 s apart, as from a camera on USB 2."""
    scene = bar_scene(WIDTH, HEIGHT)
    stamps_ms = [0, 800, 1600, 2400, 2500, 2600, 2700, 2800, 2900]
    calibration = from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (WIDTH, HEIGHT))
    with Recorder(tmp_path / "slow", calibration=calibration, source_spec="synthetic bar") as recorder:
        for i, ms in enumerate(stamps_ms):
            recorder.write(StereoFrame(scene.left, scene.right, 1_000_000_000 + ms * 1_000_000, i))
    code, report = preflight(capsys, write_config(tmp_path, f"replay:{tmp_path / 'slow'}", autopilot.port))
    assert code == CHECK_FAILED and set(failed(report)) == {"camera"}
    check = failed(report)["camera"]
    assert "at 1.2 fps, configured 10 fps" in check["found"] or "at 1.3 fps, configured 10 fps" in check["found"]
    assert "USB 3" in check["fix"]


def test_a_camera_that_stops_is_declared_lost_after_the_stall_timeout(recording):
    plan = FaultPlan(stall={2: 5.0})
    with FaultInjectingSource(ReplaySource(recording, pace="fast"), plan) as source:
        start = time.monotonic()
        arrivals, problem = read_frames(source, SAMPLED_FRAMES, stall_timeout_s=0.3)
        waited = time.monotonic() - start
    assert [frame.index for frame, _ in arrivals] == [0, 1]
    assert problem == "no frame for camera.stall_timeout_s (0.3 s)"
    assert 0.3 <= waited < 1.5


def test_a_calibration_of_another_size_is_caught_with_its_fix(recording, autopilot, tmp_path, capsys):
    other = write_opencv_file(from_rectified(FOCAL_PX, 319.5, 239.5, BASELINE_M, (640, 480)), tmp_path / "other.yaml")
    config = with_calibration(write_config(tmp_path, f"replay:{recording}", autopilot.port), other)
    code, report = preflight(capsys, config)
    assert code == CHECK_FAILED and set(failed(report)) == {"calibration"}
    check = failed(report)["calibration"]
    assert "640×480" in check["found"] and "320×256" in check["found"]
    assert "320×256 px frames" in check["fix"]


@pytest.mark.parametrize(("file_name", "ok"), [("SN5678.yaml", True), ("SN1234.yaml", False), ("calib.yaml", False)])
def test_the_calibration_must_be_the_labelled_cameras_file(recording, autopilot, tmp_path, capsys, file_name, ok):
    own = write_opencv_file(from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (WIDTH, HEIGHT)), tmp_path / file_name)
    config = with_calibration(write_config(tmp_path, f"replay:{recording}", autopilot.port), own)
    code, report = preflight(capsys, config, "--camera-serial", "5678")
    check = by_name(report)["calibration"]
    assert (code, check["status"]) == ((DONE, "pass") if ok else (CHECK_FAILED, "fail")), report
    if not ok:
        assert check["fix"] == "set camera.calibration to SN5678.conf, this camera's factory calibration"


def test_a_changed_model_file_is_caught_with_its_fix(recording, autopilot, tmp_path, capsys):
    shipped = SHIPPED_MODELS["fp32"]
    model = tmp_path / shipped.name
    shutil.copy(shipped, model)
    shutil.copy(shipped.with_suffix(".json"), model.with_suffix(".json"))
    data = bytearray(model.read_bytes())
    data[len(data) // 2] ^= 0xFF
    model.write_bytes(bytes(data))
    config = write_config(tmp_path, f"replay:{recording}", autopilot.port, f'[segmenter.learned]\nmodel = "{model}"\n')
    code, report = preflight(capsys, config)
    assert code == CHECK_FAILED and set(failed(report)) == {"models"}
    check = failed(report)["models"]
    assert "SHA-256" in check["found"] and str(model) in check["found"]
    assert "copy the model files again" in check["fix"]
    assert by_name(report)["pipeline latency"]["status"] == "skip"


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_no_heartbeat_is_caught_with_its_fix(recording, tmp_path, capsys):
    config = write_config(tmp_path, f"replay:{recording}", _free_udp_port())
    code, report = preflight(capsys, config, "--set", "mavlink.heartbeat_timeout_s=0.3")
    assert code == CHECK_FAILED and set(failed(report)) == {"autopilot heartbeat"}
    check = failed(report)["autopilot heartbeat"]
    assert "no HEARTBEAT from an autopilot" in check["found"] and "0.3 s" in check["found"]
    assert "mavlink.url" in check["fix"] and "baud" in check["fix"]
    assert by_name(report)["autopilot type"]["status"] == "skip"
    assert not any(name.startswith("parameter ") for name in by_name(report))


def test_a_wrong_prx1_type_is_caught_with_the_value_to_set(recording, tmp_path, capsys):
    with AutopilotSim(approach_flight(0.0), heartbeat_period_s=0.1, poll_s=0.005, params={"PRX1_TYPE": 0}) as sim:
        code, report = preflight(capsys, write_config(tmp_path, f"replay:{recording}", sim.port))
    assert code == CHECK_FAILED and set(failed(report)) == {"parameter PRX1_TYPE"}
    check = failed(report)["parameter PRX1_TYPE"]
    assert check["found"] == "0"
    assert check["fix"].startswith("set PRX1_TYPE = 2 (")


def test_a_pipeline_over_its_latency_budget_is_caught_with_its_fix(recording, autopilot, tmp_path, capsys):
    config = write_config(tmp_path, f"replay:{recording}", autopilot.port)
    code, report = preflight(capsys, config, "--set", "mavlink.max_result_age_s=0.001")
    assert code == CHECK_FAILED and set(failed(report)) == {"pipeline latency"}
    check = failed(report)["pipeline latency"]
    assert "budget mavlink.max_result_age_s = 1 ms" in check["found"]
    assert check["fix"].startswith("lower stereo.max_disp to the working range or roi.coarse_width")


def test_px4_is_read_with_its_own_table_and_bytewise_integers(recording, tmp_path, capsys):
    with AutopilotSim(approach_flight(0.0), heartbeat_period_s=0.1, poll_s=0.005, autopilot=MAV_AUTOPILOT_PX4) as sim:
        code, report = preflight(capsys, write_config(tmp_path, f"replay:{recording}", sim.port))
    checks = by_name(report)
    assert code == DONE, report
    assert "PX4" in checks["autopilot type"]["found"]
    assert checks["parameter MAV_SYS_ID"]["found"] == "1" and checks["parameter MAV_1_MODE"]["found"] == "2"
    assert checks["parameter CP_DIST"]["found"] == "-1"


def test_px4_collision_prevention_on_is_caught_when_cutting(recording, tmp_path, capsys):
    params = {"CP_DIST": 2.0}
    with AutopilotSim(approach_flight(0.0), poll_s=0.005, autopilot=MAV_AUTOPILOT_PX4, params=params) as sim:
        code, report = preflight(capsys, write_config(tmp_path, f"replay:{recording}", sim.port))
    assert code == CHECK_FAILED and set(failed(report)) == {"parameter CP_DIST"}
    assert failed(report)["parameter CP_DIST"]["fix"].startswith("set CP_DIST = -1 (")


def test_an_autopilot_signing_with_another_key_is_caught(recording, tmp_path, capsys):
    key_file = tmp_path / "key.bin"
    key_file.write_bytes(bytes(range(32)))
    with AutopilotSim(approach_flight(0.0), heartbeat_period_s=0.1, poll_s=0.005, signing_key=bytes(32)) as sim:
        config = write_config(tmp_path, f"replay:{recording}", sim.port, f'signing_key_file = "{key_file}"\n')
        code, report = preflight(capsys, config, "--set", "mavlink.heartbeat_timeout_s=0.5")
    assert code == CHECK_FAILED
    assert failed(report)["MAVLink signing"]["fix"] == (
        "load the same signing key on the autopilot and in mavlink.signing_key_file"
    )


def test_a_parameter_read_is_retried_and_a_parameter_nobody_holds_reads_as_none(autopilot):
    conn = open_connection(f"udpout:127.0.0.1:{autopilot.port}", source_component=191)
    try:
        autopilot.silence(0.25)  # the first request is lost, as on a radio
        assert read_parameter(conn, (1, 1), "AVOID_MARGIN", bytewise=False, timeout_s=0.2, attempts=3) == 1.0
        asked = len(autopilot.of_type("PARAM_REQUEST_READ"))
        assert read_parameter(conn, (1, 1), "NO_SUCH_PARAM", bytewise=False, timeout_s=0.1, attempts=3) is None
    finally:
        conn.close()
    assert asked >= 2
    assert [r.msg.param_id for r in autopilot.of_type("PARAM_REQUEST_READ")][asked:] == ["NO_SUCH_PARAM"] * 3


@pytest.mark.parametrize(("avoid_enable", "ok"), [(0, False), (1, False), (2, True), (3, True), (7, True)])
def test_avoid_enable_needs_its_proximity_bit(avoid_enable, ok):
    (rule,) = [rule for rule in ardupilot_rules(MavlinkConfig()) if rule.name == "AVOID_ENABLE"]
    assert rule.accepts(float(avoid_enable)) is ok


def test_a_guided_approach_adds_the_speed_limit_in_cm_per_s():
    rules = {
        rule.name: rule for rule in ardupilot_rules(MavlinkConfig(setpoint_enabled=True, setpoint_max_speed_m_s=0.5))
    }
    assert rules["WPNAV_SPEED"].wanted == "50"
    assert rules["WPNAV_SPEED"].accepts(50.0) and not rules["WPNAV_SPEED"].accepts(500.0)
    assert "WPNAV_SPEED" not in {rule.name for rule in ardupilot_rules(MavlinkConfig())}


def test_an_unreadable_configuration_is_bad_input(tmp_path, capsys):
    config = tmp_path / "drone.toml"
    config.write_text("[mavlink]\nmax_result_age_s = -1\n")
    assert branchrange_main(["preflight", "--config", str(config)]) == BAD_INPUT
    assert "max_result_age_s" in capsys.readouterr().err
