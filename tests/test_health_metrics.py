"""/metrics says every count and state /health says: a real daemon with a relay to a simulated autopilot,
both endpoints read back and compared key by key, so the two cannot drift apart again (issue 39)."""

from __future__ import annotations

import pytest
from api_scene import BASELINE_M, FOCAL_PX, bar_scene
from autopilot_sim import AutopilotSim, approach_flight
from fastapi.testclient import TestClient
from test_link_health import wait_for

from api import create_app
from api.health_metrics import FREE_TEXT, health_leaves, health_metrics, metric_name
from branchrange.config.loader import Config, pipeline_for
from branchrange.config.sections import ApiConfig, CameraConfig, MavlinkConfig
from branchrange.core.pipeline import StereoConfig
from branchrange.onboard.daemon import Daemon
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay
from camera.calibration import from_rectified
from camera.sources import FaultInjectingSource, FaultPlan, Recorder, ReplaySource, StereoFrame

TOKEN = "t0ken"
FRAMES = 6


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    scene = bar_scene()
    out = tmp_path_factory.mktemp("rec") / "bar"
    with Recorder(out, calibration=from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (320, 256))) as recorder:
        for i in range(FRAMES):
            recorder.write(StereoFrame(scene.left, scene.right, 1_000_000_000 + i * 250_000_000, i))
    return out


def _samples(text: str) -> dict[str, str]:
    """Series (name with labels) → value, of a Prometheus text body."""
    return dict(line.rsplit(" ", 1) for line in text.splitlines() if line and not line.startswith("#"))


def _series_name(samples: dict[str, str], name: str) -> str:
    """The full name (labels included) of the one series called `name`."""
    (full,) = [k for k in samples if k.startswith(name + "{")]
    return full


@pytest.fixture(scope="module")
def endpoints(recording):
    """(/health with the token, /metrics) of a daemon that ran 3 frames (one corrupt) next to a simulated autopilot."""
    with AutopilotSim(approach_flight(0.0), heartbeat_period_s=0.1) as sim:
        cfg = Config(
            camera=CameraConfig(source=f"replay:{recording}"),
            stereo=StereoConfig(max_disp=64),
            mavlink=MavlinkConfig(url=f"udpout:127.0.0.1:{sim.port}"),
        )
        relay = MavlinkRelay(cfg.mavlink, CameraMount.from_rpy())
        pipeline = pipeline_for(cfg, from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (320, 256)))
        source = FaultInjectingSource(ReplaySource(recording), FaultPlan(corrupt={1}))
        daemon = Daemon(cfg, open_source=lambda: source, pipeline=pipeline, relay=relay)
        try:
            assert daemon.run(max_frames=3) == 3
            assert wait_for(lambda: relay.link_state()["connected"], 3.0)
            with TestClient(create_app(ApiConfig(token=TOKEN), None, state=daemon)) as client:
                auth = {"Authorization": f"Bearer {TOKEN}"}
                health = client.get("/health", headers=auth).json()
                metrics = client.get("/metrics", headers=auth).text
        finally:
            daemon.close()
    return health, metrics


def test_every_count_and_state_of_health_is_a_metric(endpoints):
    health, metrics = endpoints
    samples = _samples(metrics)
    leaves = dict(health_leaves(health))
    numeric = {path: v for path, v in leaves.items() if not isinstance(v, str) and path not in FREE_TEXT}
    assert len(numeric) >= 30  # model, camera, link, peer and vehicle state: the whole body was walked
    missing = [".".join(path) for path in numeric if not any(k.split("{")[0] == metric_name(path) for k in samples)]
    assert not missing, f"/health keys without a /metrics series: {missing}"
    words = [(path, value) for path, value in leaves.items() if isinstance(value, str)]
    for path, value in words:
        info = [k for k in samples if k.startswith(f"branchrange_{path[0] if len(path) > 1 else 'health'}_info{{")]
        assert info and f'{"_".join(path[1:]) or path[0]}="{value}"' in info[0], (path, value)


def test_the_counters_and_peer_state_the_issue_named_have_the_values_health_gives(endpoints):
    health, metrics = endpoints
    samples = _samples(metrics)
    camera, peer = health["camera"], health["mavlink"]["peer"]
    assert camera["corrupt"] == 1 and camera["frames"] == 3
    for key in ("frames", "dropped", "skipped", "corrupt", "reopens", "late"):
        assert float(samples[f"branchrange_camera_{key}_total"]) == camera[key], key
    assert samples["branchrange_camera_lost"] == "0"
    assert samples["branchrange_mavlink_peer_armed"] == "1" and peer["armed"] is True
    assert int(samples["branchrange_mavlink_peer_custom_mode"]) == peer["custom_mode"] == 4
    assert samples['branchrange_mavlink_connected{system_id="1",component_id="1"}'] == "1"
    assert f'mode="{health["mavlink"]["mode"]}"' in _series_name(samples, "branchrange_mavlink_info")
    assert 'status="ok"' in _series_name(samples, "branchrange_health_info")
    assert float(samples["branchrange_mavlink_heartbeat_age_seconds"]) < 1.0
    assert "# TYPE branchrange_camera_late_total counter" in metrics
    assert "# TYPE branchrange_mavlink_peer_armed gauge" in metrics


def test_unknown_values_are_nan_and_free_text_is_no_label():
    lines = health_metrics(
        {"status": "degraded", "mavlink": {"connected": False, "peer_heartbeat_age_s": None, "last_error": "boom"}}
    )
    assert "branchrange_mavlink_heartbeat_age_seconds NaN" in lines
    assert 'branchrange_mavlink_connected{system_id="",component_id=""} 0' in lines
    assert not any("boom" in line or "last_error" in line for line in lines)
    assert 'branchrange_model_info{backend=""} 1' in health_metrics({"model": {"backend": None}})


def test_the_segmenters_out_of_distribution_reading_is_in_health_and_metrics(endpoints):
    health, metrics = endpoints
    model = health["model"]
    assert isinstance(model["segmenter_ood_flagged"], bool) and 0.0 <= model["segmenter_ood_score"] <= 1.0
    samples = _samples(metrics)
    assert any(k.split("{")[0] == "branchrange_model_segmenter_ood_flagged" for k in samples)
