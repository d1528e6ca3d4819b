"""The onboard daemon on replayed recordings: end to end to a loopback MAVLink peer, faults, shutdown."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from api_scene import BAR_DEPTH_M, BASELINE_M, FOCAL_PX, bar_scene
from branchrange.cli import main as branchrange_main
from branchrange.config import CameraConfig, Config, LogConfig, MavlinkConfig, StereoConfig, pipeline_config
from branchrange.daemon import Daemon
from branchrange.mavlink import CameraMount, MavlinkRelay
from branchrange.pipeline import Pipeline
from camera.calibration import from_rectified
from camera.sources import FaultInjectingSource, FaultPlan, Recorder, ReplaySource, StereoFrame
from mavlink_peer import LoopbackPeer, of_type

FRAMES = 12
PERIOD_NS = 250_000_000  # 4 fps: slow enough that a loaded test machine keeps up (latest frame wins)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 12-frame 4 fps recording of the bar scene with its rectified calibration."""
    scene = bar_scene()
    out = tmp_path_factory.mktemp("rec") / "bar"
    calib = from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (320, 256))
    with Recorder(out, calibration=calib, source_spec="synthetic bar") as rec:
        for i in range(FRAMES):
            rec.write(StereoFrame(scene.left, scene.right, 1_000_000_000 + i * PERIOD_NS, i))
    return out


class Listener:
    """The peer reading in a thread until `finish()` (messages arrive at >= 4 Hz, so it ends promptly)."""

    def __init__(self, peer: LoopbackPeer):
        self.peer, self.done = peer, threading.Event()
        self.thread = threading.Thread(target=peer.collect, args=(30.0, lambda _: self.done.is_set()), daemon=True)
        self.thread.start()

    def finish(self) -> None:
        self.done.set()
        self.thread.join(timeout=5)
        self.peer.close()


def test_daemon_end_to_end_sends_ground_truth_distances(recording, tmp_path):
    peer = LoopbackPeer()
    results = tmp_path / "results.jsonl"
    config = tmp_path / "onboard.toml"
    config.write_text(f'[camera]\nsource = "replay:{recording}"\n[stereo]\nmax_disp = 64\n'
                      f'[mavlink]\nurl = "udpout:127.0.0.1:{peer.port}"\n'
                      f'[log]\nresults_jsonl = "{results}"\n')
    listener = Listener(peer)
    try:
        assert branchrange_main(["daemon", "--config", str(config), "--max-frames", "4"]) == 0
    finally:
        listener.finish()
    lines = [json.loads(line) for line in results.read_text().splitlines()]
    assert len(lines) == 4 and all(r["schema"] == "branchrange/v1" for r in lines)
    expected_cm = {round(r["branches"][0]["distance_m"] * 100) for r in lines}
    dists = [d.msg for d in of_type(peer.received, "DISTANCE_SENSOR") if d.msg.current_distance <= d.msg.max_distance]
    assert dists, "no DISTANCE_SENSOR with a target arrived"
    assert {d.current_distance for d in dists} <= expected_cm
    # ground truth: the bar's front face is at 1.25 m; the pipeline puts the cut on the axis behind it
    for d in dists:
        assert d.current_distance / 100 == pytest.approx(BAR_DEPTH_M, abs=0.06)
    vects = [v.msg for v in of_type(peer.received, "DEBUG_VECT") if not math.isnan(v.msg.x)]
    assert vects and all(v.x == pytest.approx(BAR_DEPTH_M, abs=0.06) for v in vects)  # forward = z_cam
    assert of_type(peer.received, "HEARTBEAT")[0].msg.system_status == 4
    print("\nMAVLink received in the end-to-end test:")
    for name in ("HEARTBEAT", "DISTANCE_SENSOR", "OBSTACLE_DISTANCE_3D", "DEBUG_VECT"):
        print(" ", of_type(peer.received, name)[-1].msg)


def test_daemon_survives_dropped_corrupt_and_stalled_frames(recording):
    peer = LoopbackPeer()
    cfg = Config(camera=CameraConfig(source=f"replay:{recording}", stall_timeout_s=0.3),
                 stereo=StereoConfig(max_disp=64), log=LogConfig(status_interval_s=0.5),
                 mavlink=MavlinkConfig(url=f"udpout:127.0.0.1:{peer.port}"))
    plan = FaultPlan(drop={2}, corrupt={4}, disconnect={6: 3.0})
    opened = []

    def open_source():
        if not opened:
            opened.append(FaultInjectingSource(ReplaySource(recording), plan))
        else:  # the watchdog reopens the camera: it comes back at frame 8
            opened.append(ReplaySource(recording, start=8))
        return opened[-1]

    relay = MavlinkRelay(cfg.mavlink, CameraMount.from_rpy())
    pipeline = Pipeline(pipeline_config(cfg), calibration=from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (320, 256)))
    daemon = Daemon(cfg, open_source=open_source, pipeline=pipeline, relay=relay)
    listener = Listener(peer)
    try:
        processed = []
        pipeline_process = pipeline.process
        pipeline.process = lambda *a, **k: processed.append(k["index"]) or pipeline_process(*a, **k)
        daemon.run()
        time.sleep(0.3)  # heartbeats after the camera came back
    finally:
        listener.finish()
        daemon.close()
    assert daemon.corrupt == 1 and daemon.reopens == 1 and len(opened) == 2
    assert 2 not in processed and 4 not in processed and processed == sorted(processed)
    assert max(processed) == FRAMES - 1 and {0, 1, 3, 5} <= set(processed)
    statuses = [h.msg.system_status for h in of_type(peer.received, "HEARTBEAT")]
    assert 5 in statuses, "no CRITICAL heartbeat while the camera was gone"
    assert statuses[-1] == 4 and daemon.camera_lost is False


def test_sigterm_stops_the_daemon_cleanly(recording, tmp_path):
    results = tmp_path / "results.jsonl"
    config = tmp_path / "onboard.toml"
    config.write_text(f'[camera]\nsource = "replay:{recording}"\n[stereo]\nmax_disp = 64\n'
                      f'[mavlink]\nurl = "udpout:127.0.0.1:9"\n[log]\nresults_jsonl = "{results}"\n')
    proc = subprocess.Popen([sys.executable, "-m", "branchrange.cli", "daemon", "--config", str(config)],
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while (not results.exists() or not results.read_text()) and time.monotonic() < deadline:
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped after" in err
    lines = results.read_text().splitlines()
    assert 1 <= len(lines) < FRAMES and all(json.loads(line)["schema"] == "branchrange/v1" for line in lines)
