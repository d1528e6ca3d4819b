"""Offline replay of a recorded synthetic tree sequence: results, summary, overlay video, equality with the daemon."""

from __future__ import annotations

import json
import logging
import math
import shutil
import statistics

import cv2
import jsonschema
import numpy as np
import pytest
from synth_recording import HEIGHT, WIDTH, still_camera_frames, tree_scene, truth_of, write_tree_recording

from branchrange.cli import main as branchrange_main
from branchrange.commands.replay import summary_path
from branchrange.config.loader import Config, pipeline_for
from branchrange.core.frame_result import SCHEMA_PATH
from branchrange.core.frame_results import read_results, read_runs
from branchrange.core.pipeline import StereoConfig
from branchrange.offline.overlay_video import (
    DEFAULT_CODECS,
    OverlayVideoWriter,
    VideoCodec,
    VideoWriteError,
    check_video,
)
from branchrange.onboard.daemon import Daemon
from camera.sources import Recorder, ReplaySource, StereoFrame

FRAMES = 4
PERIOD_NS = 500_000_000  # 2 fps: the daemon comparison replays at this pace and must not drop frames
SCHEMA = json.loads(SCHEMA_PATH.read_text())
STAGES = ("rectify", "stereo", "masks", "cutpoints", "tracking", "total")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Four still-camera frames of the synthetic tree with ground-truth masks and calibration."""
    return write_tree_recording(tmp_path_factory.mktemp("rec") / "tree", FRAMES, PERIOD_NS)


@pytest.fixture(scope="module")
def config_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "replay.toml"
    path.write_text("[stereo]\nmax_disp = 64\n")
    return path


@pytest.fixture(scope="module")
def replayed(recording, config_file, tmp_path_factory):
    """`branchrange replay REC --out … --overlay-video … --summary` run once; its outputs."""
    out = tmp_path_factory.mktemp("out")
    results, video = out / "results.jsonl", out / "overlay.mp4"
    status = branchrange_main(
        [
            "replay",
            str(recording),
            "--out",
            str(results),
            "--overlay-video",
            str(video),
            "--summary",
            "--config",
            str(config_file),
        ]
    )
    ((_, lines),) = read_runs(results)  # the JSON records as written
    assert [r.to_json_dict() for r in read_results(results)] == lines  # read back typed, written back the same
    return status, lines, json.loads(summary_path(results).read_text()), video


def test_recording_with_masks_replays_them_unchanged(tmp_path):
    scene = tree_scene()
    frames = still_camera_frames(scene, 2, PERIOD_NS, with_masks=True)
    with Recorder(tmp_path / "rec", source_spec="test") as recorder:
        for frame in frames:
            recorder.write(frame)
        with pytest.raises(ValueError, match="lacks a mask"):
            recorder.write(StereoFrame(frames[0].left, frames[0].right, 10 * PERIOD_NS, 2))
    manifest = json.loads((tmp_path / "rec" / "recording.json").read_text())
    replayed = list(ReplaySource(tmp_path / "rec", pace="fast"))
    assert manifest["masks"] is True and len(replayed) == 2
    for original, back in zip(frames, replayed):
        assert back.mask.dtype == np.uint16 and np.array_equal(back.mask, scene.instance_mask)
        assert np.array_equal(back.left, original.left) and back.timestamp_ns == original.timestamp_ns
    assert 65535 in np.unique(replayed[0].mask)  # the trunk id survives the 16-bit PNG


def test_replay_writes_one_schema_valid_result_per_frame_from_the_recorded_masks(replayed):
    status, lines, _, _ = replayed
    assert status == 0 and len(lines) == FRAMES
    for i, result in enumerate(lines):
        jsonschema.validate(result, SCHEMA)
        assert result["frame"] == {
            "index": i,
            "timestamp_ns": 1_000_000_000 + i * PERIOD_NS,
            "width": WIDTH,
            "height": HEIGHT,
        }
        assert (
            result["masks"]["source"] == "array" and result["masks"]["trunk"] is True
        )  # ground truth, not the segmenter
        assert result["stereo"]["backend"] == "sgbm-roi" and result["stereo"]["max_disparity"] == 64
    # a still camera: the target keeps its track id and its mask instance throughout
    targets = {(b["id"], b["mask_id"]) for r in lines for b in r["branches"] if b["id"] == r["target_id"]}
    assert len(targets) == 1


def test_replay_target_distance_matches_the_ground_truth(replayed):
    _, lines, summary, _ = replayed
    scene = tree_scene()
    for result in lines:
        target = next(b for b in result["branches"] if b["id"] == result["target_id"])
        truth = truth_of(scene, target["mask_id"])
        # tolerance: see test_daemon's end-to-end test
        assert target["distance_m"] == pytest.approx(math.dist((0, 0, 0), truth.cut_point_m), abs=0.03)
        assert math.dist(target["cut_point_m"], truth.cut_point_m) < 0.05
    assert summary["distance_m"]["target"]["median"] == pytest.approx(
        math.dist((0, 0, 0), truth_of(scene, target["mask_id"]).cut_point_m), abs=0.03
    )


def test_replay_summary_counts_what_the_results_hold(replayed):
    _, lines, summary, video = replayed
    distances = [b["distance_m"] for r in lines for b in r["branches"]]
    targets = [b["distance_m"] for r in lines for b in r["branches"] if b["id"] == r["target_id"]]
    assert summary["frames"] == {
        "processed": FRAMES,
        "corrupt": 0,
        "rejected": 0,
        "lost_at_end": 0,
        "dropped_late": 0,
        "with_branches": FRAMES,
        "with_target": FRAMES,
    }
    assert summary["branches"]["detections"] == len(distances)
    assert summary["branches"]["tracks"] == len({b["id"] for r in lines for b in r["branches"]})
    assert summary["branches"]["target_tracks"] == len({r["target_id"] for r in lines})
    assert summary["distance_m"]["all"]["count"] == len(distances)
    assert summary["distance_m"]["all"]["median"] == pytest.approx(statistics.median(distances), abs=1e-4)
    assert summary["distance_m"]["all"]["min"] == pytest.approx(min(distances), abs=1e-4)
    assert summary["distance_m"]["target"]["max"] == pytest.approx(max(targets), abs=1e-4)
    assert summary["distance_m"]["target"]["std"] == pytest.approx(statistics.pstdev(targets), abs=1e-4)
    for stage in STAGES:
        times = [r["timing_ms"][stage] for r in lines]
        assert summary["timing_ms"][stage]["count"] == FRAMES
        assert summary["timing_ms"][stage]["mean"] == pytest.approx(statistics.fmean(times), abs=1e-3)
    assert summary["timing_ms"]["stereo"]["mean"] > 0 and summary["fps"] > 0
    assert summary["video"] == {"path": str(video), "codec": "mp4v"}


def test_overlay_video_reopens_with_one_frame_per_result(replayed):
    _, lines, _, video = replayed
    capture = cv2.VideoCapture(str(video))
    assert capture.isOpened()
    assert int(capture.get(cv2.CAP_PROP_FOURCC)) in (cv2.VideoWriter_fourcc(*"mp4v"), cv2.VideoWriter_fourcc(*"FMP4"))
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(1e9 / PERIOD_NS)
    decoded = []
    while (frame := capture.read())[0]:
        decoded.append(frame[1])
    capture.release()
    assert len(decoded) == len(lines) == FRAMES and decoded[0].shape == (HEIGHT, WIDTH, 3)
    # the target ring is drawn in red (RGB 255,40,40 → BGR) around the target's cut pixel
    target = next(b for b in lines[0]["branches"] if b["id"] == lines[0]["target_id"])
    u, v = (int(round(c)) for c in target["pixel"])
    window = decoded[0][max(v - 12, 0) : v + 13, max(u - 12, 0) : u + 13].reshape(-1, 3).astype(int)
    reddish = (window[:, 2] > 180) & (window[:, 1] < 110) & (window[:, 0] < 110)
    assert reddish.sum() >= 10


def test_overlay_video_falls_back_to_mjpg_avi_when_mp4v_cannot_be_written(tmp_path, caplog):
    unavailable = VideoCodec("XXXX", ".mp4", ("XXXX",))
    frames = [np.full((64, 96, 3), 40 * i, np.uint8) for i in range(3)]
    with caplog.at_level(logging.WARNING, logger="branchrange.overlay_video"):
        with OverlayVideoWriter(tmp_path / "out.mp4", 5.0, codecs=(unavailable, DEFAULT_CODECS[1])) as writer:
            for frame in frames:
                writer.write(frame)
    assert writer.path == tmp_path / "out.avi" and writer.codec.fourcc == "MJPG" and writer.path.is_file()
    assert "XXXX codec is not available" in caplog.text and "out.avi" in caplog.text
    check_video(writer.path, writer.codec, 3, (96, 64))
    with pytest.raises(VideoWriteError, match="3 frames decode; 4 were written"):
        check_video(writer.path, writer.codec, 4, (96, 64))
    with pytest.raises(VideoWriteError, match="expected one of mp4v"):
        check_video(writer.path, DEFAULT_CODECS[0], 3, (96, 64))


def test_replay_skips_a_corrupt_frame_and_counts_it(recording, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(recording, broken)
    (broken / "left" / "000001.png").write_bytes(b"not a png")
    cfg = Config(stereo=StereoConfig(max_disp=64))
    from branchrange.offline.replay import replay_recording

    summary = replay_recording(broken, cfg, tmp_path / "r.jsonl", progress=False)
    lines = [r.to_json_dict() for r in read_results(tmp_path / "r.jsonl")]
    assert [r["frame"]["index"] for r in lines] == [0, 2, 3]
    assert summary.corrupt == 1 and summary.frames == 3 and summary.to_dict()["frames"]["with_target"] == 3


def test_replay_of_a_recording_without_calibration_says_so(tmp_path, capsys):
    frame = still_camera_frames(tree_scene(), 1, PERIOD_NS, with_masks=False)[0]
    with Recorder(tmp_path / "rec") as recorder:
        recorder.write(frame)
    status = branchrange_main(["replay", str(tmp_path / "rec"), "--out", str(tmp_path / "r.jsonl")])
    assert status == 2  # bad input: nothing was processed
    assert "no calibration; set camera.calibration" in capsys.readouterr().err


def test_replay_results_equal_the_daemons_on_the_same_recording(recording, replayed, tmp_path):
    _, replay_lines, _, _ = replayed
    cfg = Config(stereo=StereoConfig(max_disp=64))
    source = ReplaySource(recording)  # paced at the recorded 2 fps, through the daemon's latest-frame-wins
    daemon = Daemon(
        cfg,
        open_source=lambda: source,
        pipeline=pipeline_for(cfg, source.calibration),
        results_path=tmp_path / "daemon.jsonl",
    )
    try:
        daemon.run()
    finally:
        daemon.close()
    daemon_lines = [r.to_json_dict() for r in read_results(tmp_path / "daemon.jsonl")]
    assert len(daemon_lines) >= FRAMES - 1  # a heavily loaded machine may make the daemon drop one
    by_index = {r["frame"]["index"]: r for r in replay_lines}
    for result in daemon_lines:
        replayed_result = by_index[result["frame"]["index"]]
        timing = ("timing_ms", "latency")  # the daemon's results also say how old they were when sent
        assert {k: v for k, v in result.items() if k not in timing} == {
            k: v for k, v in replayed_result.items() if k not in timing
        }


def _transforms_in(mcap_path) -> list:
    """The FrameTransform messages of an MCAP's tf topic, decoded through the protobuf schema the file carries."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader

    from branchrange.onboard.foxglove_sink import TOPICS

    transforms = []
    with open(mcap_path, "rb") as stream:
        for schema, _channel, message in make_reader(stream).iter_messages(topics=[TOPICS["tf"]]):
            assert schema.encoding == "protobuf"
            pool = descriptor_pool.DescriptorPool()
            for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                pool.Add(file)
            decoded = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString(message.data)
            transforms.extend(decoded.transforms)
    return transforms


def test_replay_ignores_masks_keeps_time_signals_its_start_and_places_the_camera(
    recording, config_file, tmp_path, capsys
):
    from branchrange.onboard.foxglove_sink import BODY_FRAME, CAMERA_FRAME
    from branchrange.onboard.mavlink import CameraMount
    from branchrange.onboard.mavlink.frames import quaternion_wxyz

    results, start, mcap = tmp_path / "r.jsonl", tmp_path / "start.json", tmp_path / "run.mcap"
    status = branchrange_main(
        [
            "replay",
            str(recording),
            "--out",
            str(results),
            "--config",
            str(config_file),
            "--summary",
            "--ignore-masks",
            "--pace",
            "recorded",
            "--start-signal",
            f"file:{start}",
            "--foxglove",
            str(mcap),
            "--mount-rpy-deg",
            "0",
            "-30",
            "0",
            "--mount-xyz-m",
            "0.1",
            "0",
            "0.05",
        ]
    )
    assert status == 0
    lines = [r.to_json_dict() for r in read_results(results)]
    assert lines and all(r["masks"]["source"] != "array" for r in lines)  # the segmenter's, not the recording's
    summary = json.loads(summary_path(results).read_text())
    assert summary["frames"]["processed"] + summary["frames"]["dropped_late"] == FRAMES
    assert f"{summary['frames']['dropped_late']} frames dropped as too late" in capsys.readouterr().out
    announced = json.loads(start.read_text())
    assert (announced["first_index"], announced["first_timestamp_ns"]) == (0, lines[0]["frame"]["timestamp_ns"])

    transforms = _transforms_in(mcap)
    assert len(transforms) == len(lines)  # one per frame, so a viewer joining late still has the tree
    mount = CameraMount.from_rpy((0, -30, 0), (0.1, 0, 0.05))
    w, x, y, z = quaternion_wxyz(mount.camera_to_body)
    for transform in transforms:
        assert (transform.parent_frame_id, transform.child_frame_id) == (BODY_FRAME, CAMERA_FRAME)
        t, r = transform.translation, transform.rotation
        assert (t.x, t.y, t.z) == pytest.approx((0.1, 0.0, 0.05))
        assert (r.w, r.x, r.y, r.z) == pytest.approx((w, x, y, z))


@pytest.mark.parametrize(
    "options, expected",
    [
        (["--start-at", "noon"], "start time 'noon'"),
        (["--start-signal", "udp:127.0.0.1"], "expected file:PATH or udp:HOST:PORT"),
        (["--max-late-ms", "20"], "expected milliseconds > 0 with --pace recorded"),
        (["--pace", "recorded", "--max-late-ms", "0"], "--max-late-ms is 0.0"),
    ],
)
def test_replay_refuses_bad_clock_sync_options(recording, tmp_path, capsys, options, expected):
    assert branchrange_main(["replay", str(recording), "--out", str(tmp_path / "r.jsonl"), *options]) == 2
    assert expected in capsys.readouterr().err and not (tmp_path / "r.jsonl").exists()
