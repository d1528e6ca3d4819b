"""From a ZED-style ROS 2 bag to cut points in Foxglove: the synthetic tree sequence as a recording and as bags
(MCAP and SQLite) gives the same cut points; `--foxglove` writes an MCAP that reads back with the expected
channels and counts; the live server streams the channels to a WebSocket client on loopback."""

from __future__ import annotations

import json
import logging
import re
import struct
import threading
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import PROJECT_ROOT
from mcap.reader import make_reader
from synth_recording import HEIGHT, WIDTH, still_camera_frames, tree_scene, write_tree_recording
from websockets.sync.client import connect

from branchrange.cli import main as branchrange_main
from branchrange.config.loader import Config
from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.frame_result import FrameResult
from branchrange.core.frame_results import read_results
from branchrange.core.pipeline import StereoConfig
from branchrange.offline.replay import replay_recording
from branchrange.onboard.foxglove_layout import layout, layout_text
from branchrange.onboard.foxglove_sink import (
    BODY_FRAME,
    CAMERA_FRAME,
    LOCAL_FRAME,
    TOPICS,
    FoxgloveSink,
    FoxgloveTargetError,
    FoxgloveTargets,
    parse_targets,
)
from branchrange.onboard.mavlink import CameraMount
from camera.calibration import from_rectified
from camera.sources.rosbag_writer import write_bag

FRAMES = 3
PERIOD_NS = 100_000_000
#: plumbing, not accuracy: any branch may be the target (the default asks ≥ 0.8, which few frames of this
#: small synthetic tree reach with the learned segmenter)
CFG = Config(stereo=StereoConfig(max_disp=64), cutpoints=CutPointConfig(target_min_confidence=0.3))
#: Subprotocol of the foxglove-sdk WebSocket server (Foxglove's app speaks it).
WS_SUBPROTOCOL = "foxglove.sdk.v1"


def without_timing(results: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "timing_ms"} for r in results]


def read_lines(path) -> list[dict]:
    return [r.to_json_dict() for r in read_results(path)]  # frame results; the run header is skipped


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same three frames replayed from our recording, from an MCAP bag (the CLI, with --foxglove) and from a
    SQLite bag (with observers: one failing, one keeping what it is given)."""
    root = tmp_path_factory.mktemp("foxglove")
    recording = write_tree_recording(root / "rec", FRAMES, PERIOD_NS, with_masks=False)
    assert branchrange_main(["bag-from-recording", str(recording), "--out", str(root / "bag_mcap")]) == 0
    cam = tree_scene().camera
    calibration = from_rectified(cam.focal_px, cam.cx, cam.cy, cam.baseline_m, (cam.width, cam.height))
    write_bag(
        still_camera_frames(tree_scene(), FRAMES, PERIOD_NS, with_masks=False),
        calibration,
        root / "bag_sqlite",
        storage="sqlite3",
        encoding="bgr8",
    )
    config = root / "replay.toml"
    config.write_text("[stereo]\nmax_disp = 64\n[cutpoints]\ntarget_min_confidence = 0.3\n")

    replay_recording(recording, CFG, root / "rec.jsonl", progress=False)
    status = branchrange_main(
        [
            "replay",
            str(root / "bag_mcap"),
            "--out",
            str(root / "mcap.jsonl"),
            "--summary",
            "--config",
            str(config),
            "--foxglove",
            str(root / "viz" / "run.mcap"),
            "--overlay-video",
            str(root / "bag_overlay.mp4"),
        ]
    )
    seen = []

    def failing(result, artifacts):
        raise RuntimeError("a viewer that breaks")

    failures: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = failures.append
    logging.getLogger("branchrange.replay").addHandler(handler)
    try:
        summary = replay_recording(
            f"rosbag:{root / 'bag_sqlite'}?tolerance_ms=1",
            CFG,
            root / "sqlite.jsonl",
            progress=False,
            observers=[failing, lambda r, a: seen.append((r, a))],
        )
    finally:
        logging.getLogger("branchrange.replay").removeHandler(handler)
    return {
        "root": root,
        "status": status,
        "summary": summary,
        "seen": seen,
        "failures": failures,
        "recording": read_lines(root / "rec.jsonl"),
        "mcap_bag": read_lines(root / "mcap.jsonl"),
        "sqlite_bag": read_lines(root / "sqlite.jsonl"),
        "foxglove": root / "viz" / "run.mcap",
    }


def test_bags_give_the_recordings_cut_points(runs):
    recording = runs["recording"]
    assert runs["status"] == 0 and len(recording) == FRAMES
    assert sum(len(r["branches"]) for r in recording) >= FRAMES  # the segmenter finds branches: a real comparison
    assert any(r["target_id"] is not None for r in recording)
    assert without_timing(runs["mcap_bag"]) == without_timing(recording)
    assert without_timing(runs["sqlite_bag"]) == without_timing(recording)
    stamps = [r["frame"]["timestamp_ns"] for r in runs["mcap_bag"]]
    assert stamps == [1_000_000_000 + i * PERIOD_NS for i in range(FRAMES)]
    assert runs["summary"].unpaired == {"left": 0, "right": 0}


def test_the_replay_summary_counts_unpaired_images_for_a_bag(runs):
    summary = json.loads((runs["root"] / "mcap.summary.json").read_text())
    assert summary["frames"]["processed"] == FRAMES and summary["frames"]["unpaired"] == {"left": 0, "right": 0}
    assert summary["video"]["path"].endswith("bag_overlay.mp4")  # checked to read back frame for frame
    video = cv2.VideoCapture(summary["video"]["path"])
    assert video.get(cv2.CAP_PROP_FPS) == pytest.approx(1e9 / PERIOD_NS, rel=0.01)  # the bag's rate
    video.release()


def test_a_failing_observer_is_logged_and_the_others_get_every_frame(runs):
    assert [r.getMessage() for r in runs["failures"]] == [
        f"frame {i}: observer {r.args[1]!r} failed" for i, r in enumerate(runs["failures"])
    ]
    assert len(runs["failures"]) == FRAMES and "a viewer that breaks" in str(runs["failures"][0].exc_info[1])
    seen = runs["seen"]
    assert [r.frame.index for r, _ in seen] == list(range(FRAMES))
    result, artifacts = seen[-1]
    assert artifacts.left.shape == (HEIGHT, WIDTH, 3) and artifacts.disparity.shape == (HEIGHT, WIDTH)


def test_foxglove_mcap_holds_every_channel_with_one_message_per_frame(runs):
    with runs["foxglove"].open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        counts = {summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        messages = [(channel.topic, message) for _, channel, message in reader.iter_messages(log_time_order=True)]
    results = runs["mcap_bag"]
    with_target = sum(r["target_id"] is not None for r in results)
    kinds = ("overlay", "disparity", "camera_info", "cut_points", "timing", "result", "tf")  # tf: the camera mount
    expected = {TOPICS[k]: FRAMES for k in kinds}
    expected[TOPICS["target"]] = with_target
    assert {t: n for t, n in counts.items() if n} == {t: n for t, n in expected.items() if n}
    assert schemas[TOPICS["overlay"]] == "foxglove.CompressedImage"
    assert schemas[TOPICS["cut_points"]] == "foxglove.SceneUpdate"
    assert schemas[TOPICS["target"]] == "foxglove.PoseInFrame"
    logged = [json.loads(m.data) for t, m in messages if t == TOPICS["result"]]
    assert logged == results  # the whole branchrange/v1 results, at their capture times
    assert [m.log_time for t, m in messages if t == TOPICS["result"]] == [r["frame"]["timestamp_ns"] for r in results]
    timing = [json.loads(m.data) for t, m in messages if t == TOPICS["timing"]]
    assert timing == [r["timing_ms"] for r in results]
    overlay = next(m for t, m in messages if t == TOPICS["overlay"])
    assert overlay.data.find(b"jpeg") >= 0
    jpeg = overlay.data[overlay.data.find(b"\xff\xd8") :]
    assert cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (HEIGHT, WIDTH, 3)


def test_vehicle_pose_and_mount_give_the_transform_tree_and_no_images_without_artifacts(runs, tmp_path):
    result = FrameResult.from_json_dict(runs["recording"][0])
    mount = CameraMount.from_rpy((0, -30, 0), (0.1, 0, 0.05))
    with FoxgloveSink(FoxgloveTargets(mcap=tmp_path / "tf.mcap"), mount=mount) as sink:
        sink(result, None)
        sink.set_vehicle_pose((1.0, 2.0, -3.0), (1.0, 0.0, 0.0, 0.0))
        sink(result, None)
    with (tmp_path / "tf.mcap").open("rb") as f:
        messages = [(channel.topic, message.data) for _, channel, message in make_reader(f).iter_messages()]
    tf = [data for topic, data in messages if topic == TOPICS["tf"]]
    assert len(tf) == 2 and not [t for t, _ in messages if t == TOPICS["overlay"]]
    assert BODY_FRAME.encode() in tf[0] and CAMERA_FRAME.encode() in tf[0] and LOCAL_FRAME.encode() not in tf[0]
    assert LOCAL_FRAME.encode() in tf[1]  # once the vehicle pose is known, local_ned → body_frd joins the tree


def test_newest_only_sink_returns_at_once_and_logs_the_newest_frames(runs, tmp_path):
    result, artifacts = runs["seen"][-1]
    frames = [replace(result, frame=replace(result.frame, index=i)) for i in range(6)]
    release, busy = threading.Event(), threading.Event()
    with FoxgloveSink(FoxgloveTargets(mcap=tmp_path / "newest.mcap"), newest_only=True) as sink:
        log_frame = sink._log_frame

        def held(result, artifacts):  # the sink's thread stays on the first frame until released
            busy.set()
            release.wait(10)
            log_frame(result, artifacts)

        sink._log_frame = held
        sink(frames[0], artifacts)
        assert busy.wait(10)
        for frame in frames[1:]:
            sink(frame, artifacts)  # returns although the sink's thread is busy
        release.set()
    with (tmp_path / "newest.mcap").open("rb") as f:
        logged = [
            json.loads(m.data)["frame"]["index"]
            for _, c, m in make_reader(f).iter_messages()
            if c.topic == TOPICS["result"]
        ]
    assert logged == [0, 5]  # the one in hand, then the newest: the waiting ones were replaced, not queued
    assert sink.dropped == 4 and sink.frames == 2


def test_live_server_streams_the_channels_to_a_websocket_client(runs):
    result, artifacts = runs["seen"][-1]
    with (
        FoxgloveSink(FoxgloveTargets(port=0)) as sink,
        connect(f"ws://127.0.0.1:{sink.port}", subprotocols=[WS_SUBPROTOCOL], open_timeout=5) as ws,
    ):
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 10
        while len(channels) < len(TOPICS) and time.monotonic() < deadline:
            message = json.loads(ws.recv(timeout=5))
            if message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        assert set(channels) == set(TOPICS.values())
        subscriptions = {i: topic for i, topic in enumerate(channels)}
        ws.send(
            json.dumps(
                {
                    "op": "subscribe",
                    "subscriptions": [
                        {"id": i, "channelId": channels[topic]["id"]} for i, topic in subscriptions.items()
                    ],
                }
            )
        )
        received: dict[str, bytes] = {}
        no_target = {TOPICS["target"]} if result.target is None else set()
        expected = set(TOPICS.values()) - {TOPICS["tf"]} - no_target
        while not expected <= set(received) and time.monotonic() < deadline:
            sink(result, artifacts)  # the daemon keeps sending; the subscription takes effect within a frame or two
            try:
                while True:
                    data = ws.recv(timeout=0.3)
                    if isinstance(data, bytes) and data[0] == 1:  # opcode 1: message data
                        (subscription,) = struct.unpack_from("<I", data, 1)
                        received[subscriptions[subscription]] = data[13:]
            except TimeoutError:
                pass
    assert expected <= set(received), f"missing {expected - set(received)}"
    assert json.loads(received[TOPICS["result"]]) == result.to_json_dict()


def test_parse_targets_and_its_errors():
    assert parse_targets(["out/run.mcap", "ws://0.0.0.0:8765"]) == FoxgloveTargets(
        mcap=Path("out/run.mcap"), host="0.0.0.0", port=8765
    )
    for bad in ("run.json", "ws://localhost", "ws://host:99999", "http://h:1"):
        with pytest.raises(FoxgloveTargetError, match="expected"):
            parse_targets([bad])
    with pytest.raises(FoxgloveTargetError, match="no Foxglove target"):
        FoxgloveSink(FoxgloveTargets())


def test_an_unusable_foxglove_target_is_named(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(FoxgloveTargetError, match="cannot write the MCAP file"):
        FoxgloveSink(FoxgloveTargets(mcap=tmp_path / "file" / "run.mcap"))
    with (
        FoxgloveSink(FoxgloveTargets(port=0)) as first,
        pytest.raises(FoxgloveTargetError, match=f"ws://127.0.0.1:{first.port}: cannot serve"),
    ):
        FoxgloveSink(FoxgloveTargets(port=first.port))


def test_replay_refuses_a_bad_foxglove_target(tmp_path, capsys):
    assert branchrange_main(["replay", str(tmp_path), "--out", str(tmp_path / "r.jsonl"), "--foxglove", "x.txt"]) == 2
    assert "expected an MCAP file (NAME.mcap) or a WebSocket address" in capsys.readouterr().err


def test_deploy_layout_is_the_generated_one_and_uses_only_the_sinks_topics():
    assert (PROJECT_ROOT / "deploy" / "foxglove_layout.json").read_text() == layout_text()
    text = json.dumps(layout())
    used = set(re.findall(r"/branchrange/[a-z_]+", text))
    assert used == set(TOPICS.values()) - {TOPICS["tf"]}  # transforms feed the 3D panel without a setting


def test_daemon_reads_a_bag_and_sends_what_it_publishes_to_foxglove(runs, tmp_path):
    config = tmp_path / "onboard.toml"
    results = tmp_path / "results.jsonl"
    config.write_text(f'[mavlink]\nenabled = false\n[stereo]\nmax_disp = 64\n[log]\nresults_jsonl = "{results}"\n')
    status = branchrange_main(
        [
            "daemon",
            "--config",
            str(config),
            "--source",
            f"rosbag:{runs['root'] / 'bag_mcap'}",
            "--foxglove",
            str(tmp_path / "live.mcap"),
        ]
    )
    assert status == 0
    published = read_lines(results)
    with (tmp_path / "live.mcap").open("rb") as f:
        messages = [(channel.topic, message) for _, channel, message in make_reader(f).iter_messages()]
    logged = [json.loads(m.data) for t, m in messages if t == TOPICS["result"]]
    # the sink's own thread sends the newest published result (never one the daemon did not publish), the last included
    assert published and logged and logged[-1] == published[-1]
    assert [r["frame"]["index"] for r in logged] == [r["frame"]["index"] for r in published if r in logged]
    assert len([t for t, _ in messages if t == TOPICS["tf"]]) == len(logged)  # body_frd → camera from the mount
    assert len([t for t, _ in messages if t == TOPICS["overlay"]]) == len(logged)
    by_index = {r["frame"]["index"]: r for r in runs["recording"]}
    for result in published:  # the daemon saw the bag's frames: same cut points as the replay of that frame
        replayed = by_index[result["frame"]["index"]]
        cut_points = sorted(b["cut_point_m"] for b in result["branches"])
        assert cut_points == sorted(b["cut_point_m"] for b in replayed["branches"])


def test_daemon_refuses_a_bad_foxglove_target(tmp_path, capsys):
    config = tmp_path / "onboard.toml"
    config.write_text("[mavlink]\nenabled = false\n")
    assert branchrange_main(["daemon", "--config", str(config), "--foxglove", "ws://localhost"]) == 2
    assert "expected ws://HOST:PORT" in capsys.readouterr().err
