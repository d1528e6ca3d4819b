"""The rosbag: source on small hand-made bags: encodings, stamp pairing, CameraInfo calibration, clear errors."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from branchrange.cli import main as branchrange_main
from camera.calibration import CalibrationError, from_rectified
from camera.opencv_file import write_opencv_file
from camera.rectify import Rectifier
from camera.sources import CorruptFrameError, SourceConfigError, SourceUnavailable, StereoFrame, open_source
from camera.sources.rosbag import (
    CAMERA_INFO_TYPE,
    COMPRESSED_TYPE,
    IMAGE_TYPE,
    ZED_TOPICS_BEFORE_5_1,
    BagTopics,
    RosbagSource,
    parse_rosbag_spec,
)
from camera.sources.rosbag_topics import camera_info_candidates, find_camera_info
from camera.sources.rosbag_writer import camera_info_message, image_message, write_bag

STORE = get_typestore(Stores.ROS2_HUMBLE)
TOPICS = BagTopics()
SIZE = (40, 24)  # (w, h)
FOCAL, BASELINE = 30.0, 0.12
CALIBRATION = from_rectified(FOCAL, 19.5, 11.5, BASELINE, SIZE)


def pattern(seed: int) -> np.ndarray:
    """A small RGB test image, different per seed."""
    return np.random.default_rng(seed).integers(0, 256, (SIZE[1], SIZE[0], 3), dtype=np.uint8)


def frames(count: int, period_ns: int = 100_000_000) -> list[StereoFrame]:
    return [StereoFrame(pattern(2 * i), pattern(2 * i + 1), 5_000_000_000 + i * period_ns, i) for i in range(count)]


def write_messages(path, messages, storage=StoragePlugin.MCAP):
    """A bag of (topic, msgtype, message, log time ns) rows, written in that order."""
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=storage) as writer:
        connections = {}
        for topic, msgtype, message, stamp in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=STORE)
            writer.write(connections[topic], stamp, STORE.serialize_cdr(message, msgtype))
    return path


def info_rows(stamp: int, right_p: np.ndarray | None = None):
    rect = Rectifier(CALIBRATION)
    p2 = rect.P2 if right_p is None else right_p
    return [
        (TOPICS.left_info, CAMERA_INFO_TYPE, camera_info_message(STORE.types, rect.P1, SIZE, stamp, "l"), stamp),
        (TOPICS.right_info, CAMERA_INFO_TYPE, camera_info_message(STORE.types, p2, SIZE, stamp, "r"), stamp),
    ]


def image_row(side: str, rgb: np.ndarray, stamp: int, encoding: str = "bgr8"):
    topic = TOPICS.left if side == "left" else TOPICS.right
    msgtype = COMPRESSED_TYPE if encoding in ("jpeg", "png") else IMAGE_TYPE
    return topic, msgtype, image_message(STORE.types, rgb, stamp, side, encoding), stamp


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("encoding", ["bgra8", "bgr8", "rgb8", "png"])
def test_lossless_encodings_replay_the_pixels_stamps_and_calibration(tmp_path, storage, encoding):
    sent = frames(3)
    assert write_bag(sent, CALIBRATION, tmp_path / "bag", storage=storage, encoding=encoding) == 3
    with open_source(f"rosbag:{tmp_path / 'bag'}", pace="fast") as source:
        got = list(source)
        calibration = source.calibration
    assert [f.timestamp_ns for f in got] == [f.timestamp_ns for f in sent]
    assert [f.index for f in got] == [0, 1, 2]
    for g, s in zip(got, sent):
        assert np.array_equal(g.left, s.left) and np.array_equal(g.right, s.right)
    rect = Rectifier(calibration)
    assert rect.focal_px == pytest.approx(FOCAL) and rect.baseline_m == pytest.approx(BASELINE)
    assert rect.principal_point == pytest.approx((19.5, 11.5)) and calibration.image_size == SIZE


def test_mono8_and_jpeg_decode_to_rgb(tmp_path):
    sent = frames(1)
    write_bag(sent, CALIBRATION, tmp_path / "mono8", encoding="mono8")
    with RosbagSource(tmp_path / "mono8", pace="fast") as source:
        (frame,) = list(source)
    assert frame.left.shape == (SIZE[1], SIZE[0], 3) and frame.left.dtype == np.uint8
    assert np.array_equal(frame.left[..., 0], frame.left[..., 2])  # grey: the luma of the original
    luma = sent[0].left.astype(float) @ [0.299, 0.587, 0.114]
    assert np.abs(frame.left[..., 0] - luma).max() <= 1

    y, x = np.mgrid[0 : SIZE[1], 0 : SIZE[0]]
    smooth = np.stack([x * 6, y * 10, np.full_like(x, 200)], axis=-1).astype(np.uint8)  # R, G, B all different
    write_bag([StereoFrame(smooth, smooth, 0, 0)], CALIBRATION, tmp_path / "jpeg", encoding="jpeg")
    with RosbagSource(tmp_path / "jpeg", pace="fast") as source:
        (frame,) = list(source)
    assert np.abs(frame.left.astype(int) - smooth).mean() < 4  # lossy, but the same picture in RGB order


def test_left_and_right_pair_by_stamp_within_the_tolerance_and_the_rest_is_counted(tmp_path, caplog):
    ms = 1_000_000
    rows = info_rows(0)
    # pair 0: right 2 ms late (paired); a left alone at 50 ms; pair 1 at 100 ms with the right first;
    # a right alone at 150 ms; pair 2 at 200 ms; a trailing left at 300 ms.
    rows += [
        image_row("left", pattern(0), 0),
        image_row("right", pattern(1), 2 * ms),
        image_row("left", pattern(2), 50 * ms),
        image_row("right", pattern(3), 100 * ms),
        image_row("left", pattern(4), 100 * ms),
        image_row("right", pattern(5), 150 * ms),
        image_row("left", pattern(6), 200 * ms),
        image_row("right", pattern(7), 201 * ms),
        image_row("left", pattern(8), 300 * ms),
    ]
    path = write_messages(tmp_path / "bag", rows)
    with open_source(f"rosbag:{path}?tolerance_ms=5", pace="fast") as source:
        got = list(source)
        unpaired = source.unpaired
    assert [f.timestamp_ns for f in got] == [0, 100 * ms, 200 * ms]
    assert [
        np.array_equal(f.left, pattern(s)) and np.array_equal(f.right, pattern(s + 1)) for f, s in zip(got, (0, 3, 6))
    ] == [True, False, True]  # pair 1: right was pattern(3), left pattern(4)
    assert np.array_equal(got[1].left, pattern(4)) and np.array_equal(got[1].right, pattern(3))
    assert unpaired == {"left": 2, "right": 1}
    assert "2 left and 1 right images had no partner within 5.0 ms" in caplog.text
    with open_source(f"rosbag:{path}?tolerance_ms=1", pace="fast") as strict:  # 2 ms is now too far
        assert [f.timestamp_ns for f in strict] == [100 * ms, 200 * ms]


def test_recorded_pace_and_start_and_loop(tmp_path):
    write_bag(frames(3, period_ns=20_000_000), CALIBRATION, tmp_path / "bag")
    now = [0]
    released = []

    def wait(seconds: float) -> bool:  # no real sleeping: the clock jumps to the end of the wait
        now[0] += round(seconds * 1e9)
        return False

    source = RosbagSource(tmp_path / "bag", start=1, loop=True, clock=lambda: now[0])
    source._stop.wait = wait
    for _ in range(4):
        frame = next(source)
        released.append((frame.index, now[0]))
    source.close()
    # start=1; each pass adds the bag's pair count, as ReplaySource; each frame released at its stamp's
    # offset from the first, the loop seam one period after the last frame
    assert released == [(1, 0), (2, 20_000_000), (4, 40_000_000), (5, 60_000_000)]


def test_a_missing_topic_names_the_topics_the_bag_has(tmp_path):
    write_bag(frames(1), CALIBRATION, tmp_path / "bag")
    with pytest.raises(SourceConfigError) as error:
        open_source(f"rosbag:{tmp_path / 'bag'}?left=/camera/left/image_raw")
    message = str(error.value)
    assert "left topic /camera/left/image_raw is not in the bag" in message
    assert f"{TOPICS.left} (sensor_msgs/msg/Image, 1 messages)" in message and TOPICS.right_info in message


def test_the_zed_wrappers_topics_since_5_1_are_the_default(tmp_path):
    assert TOPICS == BagTopics(
        "/zed/zed_node/left/color/rect/image",
        "/zed/zed_node/right/color/rect/image",
        "/zed/zed_node/left/color/rect/camera_info",
        "/zed/zed_node/right/color/rect/camera_info",
    )
    write_bag(frames(2), CALIBRATION, tmp_path / "bag")
    with RosbagSource(tmp_path / "bag", pace="fast") as source:
        assert source.topics == TOPICS and len(list(source)) == 2


def test_a_bag_of_a_zed_wrapper_before_5_1_is_read_with_its_topics(tmp_path, caplog):
    sent = frames(2)
    write_bag(sent, CALIBRATION, tmp_path / "bag", storage="sqlite3", topics=ZED_TOPICS_BEFORE_5_1)
    caplog.set_level("INFO", logger="camera.sources.rosbag")
    with open_source(f"rosbag:{tmp_path / 'bag'}", pace="fast") as source:
        got = list(source)
        assert source.topics == ZED_TOPICS_BEFORE_5_1
        assert Rectifier(source.calibration).baseline_m == pytest.approx(BASELINE)  # its camera_info topics too
    assert [f.timestamp_ns for f in got] == [f.timestamp_ns for f in sent]
    assert "ZED wrapper's topics of before version 5.1" in caplog.text


def test_topics_named_in_the_spec_are_not_second_guessed(tmp_path):
    write_bag(frames(1), CALIBRATION, tmp_path / "bag", topics=ZED_TOPICS_BEFORE_5_1)
    with pytest.raises(SourceConfigError, match=f"the left topic {TOPICS.left} is not in the bag"):
        open_source(f"rosbag:{tmp_path / 'bag'}?right={ZED_TOPICS_BEFORE_5_1.right}")


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_truncated_bag_is_named_truncated_with_what_to_do(tmp_path, storage):
    write_bag(frames(6), CALIBRATION, tmp_path / "bag", storage=storage)
    (data,) = [p for p in (tmp_path / "bag").iterdir() if p.suffix in (".mcap", ".db3")]
    data.write_bytes(data.read_bytes()[: data.stat().st_size // 2])
    for path in (tmp_path / "bag", data):
        with pytest.raises(SourceUnavailable) as error:
            open_source(f"rosbag:{path}")
        assert str(error.value) == (
            f"{path} is truncated or unfinished ({data.name} begins as a bag file but ends early or is damaged): "
            f"record it again or run `ros2 bag reindex {tmp_path / 'bag'}`"
        )


def test_a_bag_directory_without_its_metadata_is_unfinished(tmp_path, capsys):
    write_bag(frames(2), CALIBRATION, tmp_path / "bag")
    (tmp_path / "bag" / "metadata.yaml").unlink()  # rosbag2 writes it last: a recording killed before
    with pytest.raises(SourceUnavailable, match=r"is truncated or unfinished \(no metadata\.yaml"):
        open_source(f"rosbag:{tmp_path / 'bag'}")
    assert branchrange_main(["replay", str(tmp_path / "bag"), "--out", str(tmp_path / "r.jsonl")]) == 2
    assert "truncated or unfinished" in capsys.readouterr().err  # recognised as a bag without its metadata


def test_topics_from_the_spec_override_the_zed_defaults(tmp_path):
    custom = BagTopics("/cam/l/image", "/cam/r/image", "/cam/l/info", "/cam/r/info")
    write_bag(frames(2), CALIBRATION, tmp_path / "bag", topics=custom)
    spec = (
        f"rosbag:{tmp_path / 'bag'}?left=/cam/l/image&right=/cam/r/image&left_info=/cam/l/info&right_info=/cam/r/info"
    )
    with open_source(spec, pace="fast") as source:
        assert len(list(source)) == 2


def test_an_unsupported_encoding_is_named(tmp_path):
    msg = STORE.types[IMAGE_TYPE](
        header=image_message(STORE.types, pattern(0), 0, "l", "rgb8").header,
        height=SIZE[1],
        width=SIZE[0],
        encoding="16UC1",
        is_bigendian=0,
        step=2 * SIZE[0],
        data=np.zeros(2 * SIZE[0] * SIZE[1], np.uint8),
    )
    path = write_messages(
        tmp_path / "bag", info_rows(0) + [(TOPICS.left, IMAGE_TYPE, msg, 0), (TOPICS.right, IMAGE_TYPE, msg, 0)]
    )
    with open_source(f"rosbag:{path}", pace="fast") as source, pytest.raises(SourceConfigError) as error:
        next(source)
    assert "encoding '16UC1' is not supported" in str(error.value) and "bgra8" in str(error.value)


def test_an_undecodable_compressed_image_is_a_corrupt_frame_and_the_next_one_comes(tmp_path):
    header = image_row("left", pattern(0), 0)[2].header
    bad = STORE.types[COMPRESSED_TYPE](header=header, format="jpeg", data=np.arange(50, dtype=np.uint8))
    rows = info_rows(0) + [
        (TOPICS.left, COMPRESSED_TYPE, bad, 0),
        image_row("right", pattern(1), 0, "png"),
        image_row("left", pattern(2), 10, "png"),
        image_row("right", pattern(3), 10, "png"),
    ]
    with open_source(f"rosbag:{write_messages(tmp_path / 'bag', rows)}", pace="fast") as source:
        with pytest.raises(CorruptFrameError, match="does not decode"):
            next(source)
        assert np.array_equal(next(source).left, pattern(2))


def test_camera_info_with_a_baseline_in_the_wrong_unit_is_refused(tmp_path):
    p2 = Rectifier(CALIBRATION).P2.copy()
    p2[0, 3] = -BASELINE  # Tx = -B instead of -fx·B (seen in old ZED wrappers)
    path = write_messages(
        tmp_path / "bag",
        info_rows(0, right_p=p2) + [image_row("left", pattern(0), 0), image_row("right", pattern(1), 0)],
    )
    with pytest.raises(CalibrationError, match="Tx = -fx·B"):
        open_source(f"rosbag:{path}")


def test_without_camera_info_a_calibration_file_is_needed_and_used(tmp_path):
    path = write_messages(tmp_path / "bag", [image_row("left", pattern(0), 0), image_row("right", pattern(1), 0)])
    with pytest.raises(SourceConfigError, match="no sensor_msgs/msg/CameraInfo topic next to the image topic"):
        open_source(f"rosbag:{path}")
    calib_file = tmp_path / "calib.yaml"
    write_opencv_file(from_rectified(FOCAL, 19.5, 11.5, 0.2, SIZE), calib_file)
    with open_source(f"rosbag:{path}", calibration=calib_file, pace="fast") as source:
        assert Rectifier(source.calibration).baseline_m == pytest.approx(0.2)
        assert len(list(source)) == 1


@pytest.mark.parametrize(
    "rest, expected",
    [
        ("", "expected rosbag:PATH"),
        ("bag?lft=/a", "option 'lft' is unknown"),
        ("bag?tolerance_ms=abc", "tolerance_ms is 'abc'"),
        ("bag?left=camera/left", "expected a topic name starting with /"),
    ],
)
def test_bad_specs_say_what_is_accepted(rest, expected):
    with pytest.raises(SourceConfigError, match=expected):
        parse_rosbag_spec(rest)


def test_a_path_that_is_no_bag_is_unavailable(tmp_path):
    with pytest.raises(SourceUnavailable, match="no such bag"):
        open_source(f"rosbag:{tmp_path / 'nothing'}")
    (tmp_path / "notes.mcap").write_bytes(b"not an mcap file")
    with pytest.raises(SourceUnavailable, match="not a readable ROS 2 bag"):
        open_source(f"rosbag:{tmp_path / 'notes.mcap'}")


def test_bag_from_recording_command_and_its_errors(tmp_path, capsys):
    from camera.sources import Recorder

    with Recorder(tmp_path / "rec", calibration=CALIBRATION) as recorder:
        for frame in frames(2):
            recorder.write(frame)
    assert (
        branchrange_main(
            [
                "bag-from-recording",
                str(tmp_path / "rec"),
                "--out",
                str(tmp_path / "bag"),
                "--storage",
                "sqlite3",
                "--left-topic",
                "/cam/left/image",
                "--left-info-topic",
                "/cam/left/camera_info",
            ]
        )
        == 0
    )
    assert "wrote 2 pairs" in capsys.readouterr().out
    with open_source(f"rosbag:{tmp_path / 'bag'}?left=/cam/left/image", pace="fast") as source:
        assert [f.index for f in source] == [0, 1]
        assert source.topics.left_info == "/cam/left/camera_info"  # found next to the left image
    assert branchrange_main(["bag-from-recording", str(tmp_path / "rec"), "--out", str(tmp_path / "bag")]) == 2
    assert "exists already" in capsys.readouterr().err
    assert (
        branchrange_main(
            ["bag-from-recording", str(tmp_path / "rec"), "--out", str(tmp_path / "b2"), "--encoding", "yuv422"]
        )
        == 2
    )
    assert "encoding is 'yuv422'; expected one of bgra8" in capsys.readouterr().err


def test_a_bag_spec_takes_the_replay_options(tmp_path):
    sent = frames(2)
    write_bag(sent, CALIBRATION, tmp_path / "bag")
    signal = tmp_path / "start.json"
    spec = f"rosbag:{tmp_path / 'bag'}?tolerance_ms=2&start_signal=file:{signal}&max_late_ms=5"
    with open_source(spec, pace="recorded") as source:
        first = next(source)
        assert source.late_limit_ns == 5_000_000
    start = json.loads(signal.read_text())
    assert start["first_timestamp_ns"] == first.timestamp_ns == sent[0].timestamp_ns
    with pytest.raises(SourceConfigError, match="ignore_masks is 'maybe'"):
        open_source(f"rosbag:{tmp_path / 'bag'}?ignore_masks=maybe")


def compressed(topics: BagTopics) -> BagTopics:
    """The same camera's topics as image_transport's compressed plugin publishes its images."""
    return replace(topics, left=f"{topics.left}/compressed", right=f"{topics.right}/compressed")


@pytest.mark.parametrize(
    "topics, encoding",
    [
        (TOPICS, "bgra8"),
        (compressed(TOPICS), "png"),
        (ZED_TOPICS_BEFORE_5_1, "bgra8"),
        (compressed(ZED_TOPICS_BEFORE_5_1), "png"),
    ],
    ids=["5.1-raw", "5.1-compressed", "before-5.1-raw", "before-5.1-compressed"],
)
def test_a_zed_bag_of_either_wrapper_replays_with_only_its_image_topics_named(tmp_path, topics, encoding):
    sent = frames(2)
    write_bag(sent, CALIBRATION, tmp_path / "bag", encoding=encoding, topics=topics)
    with open_source(f"rosbag:{tmp_path / 'bag'}?left={topics.left}&right={topics.right}", pace="fast") as source:
        got = list(source)
        assert source.topics == topics  # the camera_info topics found next to the images
        rect = Rectifier(source.calibration)
    assert rect.focal_px == pytest.approx(FOCAL) and rect.baseline_m == pytest.approx(BASELINE)
    assert [f.timestamp_ns for f in got] == [f.timestamp_ns for f in sent]
    assert all(np.array_equal(g.left, s.left) and np.array_equal(g.right, s.right) for g, s in zip(got, sent))


def test_the_camera_info_topics_looked_for_walk_up_to_the_namespace_the_images_share():
    left, right = "/zed/zed_node/left/color/rect/image/compressed", "/zed/zed_node/right/color/rect/image/compressed"
    assert camera_info_candidates(left, right) == [
        "/zed/zed_node/left/color/rect/image/camera_info",
        "/zed/zed_node/left/color/rect/camera_info",
        "/zed/zed_node/left/color/camera_info",
        "/zed/zed_node/left/camera_info",
    ]  # not /zed/zed_node/camera_info: it would be both cameras' calibration
    assert camera_info_candidates("/cam/left_image", "/cam/right_image") == []
    infos = {"/zed/zed_node/left/camera_info", "/zed/zed_node/left/color/rect/camera_info"}
    assert find_camera_info(left, right, infos) == "/zed/zed_node/left/color/rect/camera_info"  # the nearest
    assert find_camera_info(right, left, infos) is None


def test_a_camera_info_topic_named_in_the_spec_wins_over_the_one_next_to_the_image(tmp_path):
    rect = Rectifier(CALIBRATION)
    wide = Rectifier(from_rectified(FOCAL, 19.5, 11.5, 0.3, SIZE))
    rows = [
        ("/cam/left/camera_info", CAMERA_INFO_TYPE, camera_info_message(STORE.types, rect.P1, SIZE, 0, "l"), 0),
        ("/cam/right/camera_info", CAMERA_INFO_TYPE, camera_info_message(STORE.types, rect.P2, SIZE, 0, "r"), 0),
        ("/calib/right", CAMERA_INFO_TYPE, camera_info_message(STORE.types, wide.P2, SIZE, 0, "r"), 0),
        ("/cam/left/image", IMAGE_TYPE, image_message(STORE.types, pattern(0), 0, "l", "rgb8"), 0),
        ("/cam/right/image", IMAGE_TYPE, image_message(STORE.types, pattern(1), 0, "r", "rgb8"), 0),
    ]
    path = write_messages(tmp_path / "bag", rows)
    images = "left=/cam/left/image&right=/cam/right/image"
    with open_source(f"rosbag:{path}?{images}", pace="fast") as found:
        assert Rectifier(found.calibration).baseline_m == pytest.approx(BASELINE)
    with open_source(f"rosbag:{path}?{images}&right_info=/calib/right", pace="fast") as named:
        assert named.topics.right_info == "/calib/right" and named.topics.left_info == "/cam/left/camera_info"
        assert Rectifier(named.calibration).baseline_m == pytest.approx(0.3)


def test_no_camera_info_next_to_the_images_names_what_was_looked_for_and_the_bag_topics(tmp_path):
    rows = [
        ("/cam/left/image", IMAGE_TYPE, image_message(STORE.types, pattern(0), 0, "l", "rgb8"), 0),
        ("/cam/right/image", IMAGE_TYPE, image_message(STORE.types, pattern(1), 0, "r", "rgb8"), 0),
        (
            "/cam/camera_info",
            CAMERA_INFO_TYPE,
            camera_info_message(STORE.types, Rectifier(CALIBRATION).P1, SIZE, 0, "l"),
            0,
        ),
    ]
    path = write_messages(tmp_path / "bag", rows)
    with pytest.raises(SourceConfigError) as error:
        open_source(f"rosbag:{path}?left=/cam/left/image&right=/cam/right/image")
    message = str(error.value)
    assert "no sensor_msgs/msg/CameraInfo topic next to the image topic /cam/left/image" in message
    assert "(looked for /cam/left/camera_info)" in message and "rosbag:PATH?left_info=TOPIC" in message
    assert "/cam/camera_info (sensor_msgs/msg/CameraInfo, 1 messages)" in message  # the bag's topics
    calib_file = tmp_path / "calib.yaml"
    write_opencv_file(CALIBRATION, calib_file)  # with a calibration file no CameraInfo is needed
    with open_source(f"rosbag:{path}?left=/cam/left/image&right=/cam/right/image", calibration=calib_file) as source:
        assert source.topics.left_info == "" and len(list(source)) == 1


def test_replay_of_a_bag_before_5_1_with_only_its_compressed_image_topics_named_exits_0(tmp_path, capsys):
    """The issue's case: `branchrange replay 'rosbag:BAG?left=…/image_rect_color/compressed&right=…'` exited 2."""
    topics = compressed(ZED_TOPICS_BEFORE_5_1)
    write_bag(frames(2), CALIBRATION, tmp_path / "bag", encoding="png", topics=topics)
    spec = f"rosbag:{tmp_path / 'bag'}?left={topics.left}&right={topics.right}"
    assert branchrange_main(["replay", spec, "--out", str(tmp_path / "r.jsonl")]) == 0
    header, *results = [json.loads(line) for line in (tmp_path / "r.jsonl").read_text().splitlines()]
    assert header["source"] == spec and len(results) == 2
    assert all(r["camera"]["baseline_m"] == pytest.approx(BASELINE) for r in results)  # from its camera_info
