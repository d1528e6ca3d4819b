"""Frame sources: recording and replay, fault injection, latest-frame-wins, ZED over UVC with a file-fed capture."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from camera import CalibrationError, StereoCalibration, from_zed_conf, load_calibration
from camera.sources import (
    Backoff,
    CorruptFrameError,
    FaultInjectingSource,
    FaultPlan,
    LatestFrameSource,
    Recorder,
    RecordingFormatError,
    ReplaySource,
    SourceConfigError,
    SourceDisconnected,
    SourceUnavailable,
    StereoFrame,
    StereoSource,
    ZedUvcSource,
    open_source,
    record,
)
from camera.sources.spec import parse_zed_spec

SIZE = (64, 48)
PERIOD_NS = 40_000_000
T0 = 5_000_000_000


def make_frames(count: int, size: tuple[int, int] = SIZE, seed: int = 0) -> list[StereoFrame]:
    """Distinct random RGB pairs with timestamps PERIOD_NS apart."""
    rng = np.random.default_rng(seed)
    width, height = size
    return [
        StereoFrame(
            rng.integers(0, 256, (height, width, 3), dtype=np.uint8),
            rng.integers(0, 256, (height, width, 3), dtype=np.uint8),
            T0 + i * PERIOD_NS,
            i,
        )
        for i in range(count)
    ]


@pytest.fixture
def calibration() -> StereoCalibration:
    k = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    return StereoCalibration(
        k, np.array([-0.1, 0.01, 0, 0, 0]), k, np.zeros(5), np.eye(3), np.array([-0.063, 0, 0]), SIZE
    )


@pytest.fixture
def frames() -> list[StereoFrame]:
    return make_frames(6)


@pytest.fixture
def recording(tmp_path: Path, frames: list[StereoFrame], calibration: StereoCalibration) -> Path:
    out = tmp_path / "rec"
    with Recorder(out, calibration=calibration, source_spec="test:frames") as recorder:
        assert record(iter(frames), recorder) == len(frames)
    return out


def _same(a: StereoFrame, b: StereoFrame) -> bool:
    return np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)


# ---------------------------------------------------------------- record → replay


def test_record_then_replay_gives_back_the_same_frames(
    recording: Path, frames: list[StereoFrame], calibration: StereoCalibration
) -> None:
    with ReplaySource(recording, pace="fast") as source:
        assert isinstance(source, StereoSource)
        replayed = list(source)
        assert source.calibration == calibration
    assert len(replayed) == len(frames)
    for original, copy in zip(frames, replayed):
        assert _same(original, copy)
        assert (copy.timestamp_ns, copy.index) == (original.timestamp_ns, original.index)
        assert copy.left.dtype == np.uint8 and copy.left.shape == (SIZE[1], SIZE[0], 3)
    manifest = json.loads((recording / "recording.json").read_text())
    assert manifest["frames"] == 6 and manifest["complete"] is True
    assert (manifest["width"], manifest["height"]) == SIZE
    assert manifest["fps"] == pytest.approx(25.0)
    assert manifest["source"] == "test:frames" and manifest["calibration"] == "calibration.yaml"
    assert (recording / "timestamps.csv").read_text().splitlines()[1] == f"0,{T0},left/000000.png,right/000000.png"


def test_record_stops_at_the_frame_limit(tmp_path: Path, frames: list[StereoFrame]) -> None:
    seen: list[int] = []
    with Recorder(tmp_path / "short") as recorder:
        assert record(iter(frames), recorder, limit=3, on_frame=lambda f: seen.append(f.index)) == 3
    assert seen == [0, 1, 2]
    assert [f.index for f in ReplaySource(tmp_path / "short", pace="fast")] == [0, 1, 2]


def test_recorder_refuses_size_change_and_old_timestamps(tmp_path: Path, frames: list[StereoFrame]) -> None:
    with Recorder(tmp_path / "r") as recorder:
        recorder.write(frames[1])
        with pytest.raises(ValueError, match="does not follow"):
            recorder.write(frames[0])
        with pytest.raises(ValueError, match="32×24; the recording is 64×48"):
            recorder.write(make_frames(3, size=(32, 24))[2])
    with pytest.raises(FileExistsError, match="not empty"):
        Recorder(tmp_path / "r")


def test_interrupted_recording_still_replays(tmp_path: Path, frames: list[StereoFrame]) -> None:
    recorder = Recorder(tmp_path / "cut")
    for frame in frames[:4]:
        recorder.write(frame)
    # no close(): the manifest still says complete: false, timestamps.csv has every written row
    assert json.loads((tmp_path / "cut" / "recording.json").read_text())["complete"] is False
    assert [f.index for f in ReplaySource(tmp_path / "cut", pace="fast")] == [0, 1, 2, 3]
    recorder.close()


def test_interrupted_recording_keeps_its_size_and_masks(tmp_path: Path, frames: list[StereoFrame]) -> None:
    masked = [
        StereoFrame(f.left, f.right, f.timestamp_ns, f.index, np.full((SIZE[1], SIZE[0]), i + 1, np.uint16))
        for i, f in enumerate(frames[:3])
    ]
    recorder = Recorder(tmp_path / "cut")
    for frame in masked:
        recorder.write(frame)
    # no close(): the manifest written after the first frame already says masks and size
    manifest = json.loads((tmp_path / "cut" / "recording.json").read_text())
    assert manifest["complete"] is False and manifest["masks"] is True
    assert (manifest["width"], manifest["height"]) == SIZE
    replayed = ReplaySource(tmp_path / "cut", pace="fast")
    assert replayed.frame_size == SIZE
    assert [int(f.mask[0, 0]) for f in replayed] == [1, 2, 3]
    recorder.close()


def test_replay_starts_at_a_frame_and_loops_with_growing_index_and_time(
    recording: Path, frames: list[StereoFrame]
) -> None:
    source = ReplaySource(recording, pace="fast", loop=True, start=4)
    got = [next(source) for _ in range(6)]
    source.close()
    assert [f.index for f in got] == [4, 5, 10, 11, 16, 17]
    for frame, original in zip(got, [frames[4], frames[5]] * 3):
        assert _same(frame, original)
    stamps = [f.timestamp_ns for f in got]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert stamps[2] - stamps[1] == PERIOD_NS  # the loop seam keeps the recorded frame period
    with pytest.raises(StopIteration):
        next(source)


def test_replay_paces_at_recorded_speed_or_as_fast_as_possible(recording: Path) -> None:
    started = time.monotonic()
    paced_source = ReplaySource(recording, pace="recorded")
    assert len(list(paced_source)) + paced_source.dropped_late == 6  # a busy machine may make one too late
    paced = time.monotonic() - started
    started = time.monotonic()
    list(ReplaySource(recording, pace="fast"))
    fast = time.monotonic() - started
    assert paced >= 5 * PERIOD_NS / 1e9 * 0.95
    assert fast < paced / 2


def test_corrupt_image_raises_for_that_frame_and_replay_goes_on(recording: Path) -> None:
    (recording / "right" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    source = ReplaySource(recording, pace="fast")
    assert [next(source).index for _ in range(2)] == [0, 1]
    with pytest.raises(CorruptFrameError, match=r"right/000002\.png: cannot be decoded"):
        next(source)
    assert [f.index for f in source] == [3, 4, 5]


def test_replay_of_bad_directories_names_the_file(tmp_path: Path, recording: Path) -> None:
    with pytest.raises(SourceUnavailable, match="no such recording"):
        ReplaySource(tmp_path / "nowhere")
    (recording / "timestamps.csv").write_text(
        "index,timestamp_ns,left,right\n0,5,left/a.png,right/a.png\n1,5,left/b.png,right/b.png\n"
    )
    with pytest.raises(RecordingFormatError, match=r"timestamps\.csv: line 3: timestamp_ns 5 does not increase"):
        ReplaySource(recording)
    (recording / "recording.json").unlink()
    with pytest.raises(RecordingFormatError, match=r"recording\.json: missing"):
        ReplaySource(recording)
    with pytest.raises(SourceConfigError, match="pace"):
        ReplaySource(recording, pace="slow")


def test_side_by_side_video_replays_losslessly(
    tmp_path: Path, frames: list[StereoFrame], calibration: StereoCalibration
) -> None:
    path = tmp_path / "sbs.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (2 * SIZE[0], SIZE[1]))
    assert writer.isOpened(), "OpenCV's FFmpeg backend cannot write FFV1 here"
    for frame in frames:
        writer.write(cv2.cvtColor(np.hstack([frame.left, frame.right]), cv2.COLOR_RGB2BGR))
    writer.release()
    source = ReplaySource(path, pace="fast", start=2, calibration=calibration)
    got = list(source)
    assert source.calibration is calibration and source.frame_count == 6
    assert [f.index for f in got] == [2, 3, 4, 5]
    assert [f.timestamp_ns for f in got] == [i * PERIOD_NS for i in (2, 3, 4, 5)]
    for frame, original in zip(got, frames[2:]):
        assert _same(frame, original)


# ---------------------------------------------------------------- faults


class FakeTime:
    """A clock that only moves when something sleeps on it; records every sleep."""

    def __init__(self) -> None:
        self.now = 0.0
        self.sleeps: list[float] = []

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds

    def clock(self) -> float:
        return self.now


def test_fault_injector_drops_stalls_and_corrupts(recording: Path) -> None:
    fake = FakeTime()
    plan = FaultPlan(drop={1}, stall={3: 0.25}, corrupt={4})
    source = FaultInjectingSource(ReplaySource(recording, pace="fast"), plan, sleep=fake.sleep, clock=fake.clock)
    assert [next(source).index for _ in range(3)] == [0, 2, 3]  # frame 1 vanished; 3 came late
    assert fake.sleeps == [0.25]
    with pytest.raises(CorruptFrameError, match="position 4"):
        next(source)
    assert [f.index for f in source] == [5]
    assert source.injected == [(1, "drop"), (3, "stall"), (4, "corrupt")]
    assert not source.is_lost


def test_fault_injector_disconnect_blocks_while_lost(recording: Path) -> None:
    lost_while_sleeping: list[bool] = []
    source: FaultInjectingSource

    def sleep(seconds: float) -> None:
        lost_while_sleeping.append(source.is_lost)

    source = FaultInjectingSource(ReplaySource(recording, pace="fast"), FaultPlan(disconnect={2: 1.5}), sleep=sleep)
    assert [f.index for f in source] == [0, 1, 2, 3, 4, 5]
    assert lost_while_sleeping == [True]
    assert not source.is_lost


def test_fault_injector_disconnect_raises_until_the_outage_ends(recording: Path) -> None:
    fake = FakeTime()
    plan = FaultPlan(disconnect={1: 2.0}, disconnect_raises=True)
    source = FaultInjectingSource(ReplaySource(recording, pace="fast"), plan, sleep=fake.sleep, clock=fake.clock)
    assert next(source).index == 0
    for _ in range(4):  # at 0.0, 0.6, 1.2 and 1.8 s the 2 s outage is still on
        with pytest.raises(SourceDisconnected):
            next(source)
        assert source.is_lost
        fake.now += 0.6
    assert next(source).index == 1 and not source.is_lost
    assert fake.sleeps == []


# ---------------------------------------------------------------- latest frame wins


def test_latest_frame_source_hands_out_only_the_newest(recording: Path) -> None:
    inner = ReplaySource(recording, pace="fast")
    latest = LatestFrameSource(inner)
    latest._thread.join(timeout=10)  # let the capture thread drain the whole recording
    frame = latest.get(timeout=1)
    assert frame is not None and frame.index == 5
    assert latest.dropped == 5
    with pytest.raises(StopIteration):
        latest.get(timeout=1)
    latest.close()


def test_latest_frame_source_passes_corrupt_frames_on_and_keeps_capturing(recording: Path) -> None:
    faulty = FaultInjectingSource(ReplaySource(recording, pace="recorded"), FaultPlan(corrupt={1}))
    with LatestFrameSource(faulty) as latest:
        received, errors = [], []
        while True:
            try:
                received.append(next(latest).index)
            except CorruptFrameError:
                errors.append(True)
            except StopIteration:
                break
    assert errors == [True]
    assert received[-1] == 5 and 1 not in received
    assert received == sorted(received)


def test_latest_frame_source_times_out_with_none(recording: Path) -> None:
    # the next frame 30 s late (the wait ends at close): a test thread kept off the CPU for the 40 ms of the
    # next paced frame would find it there
    stalled = FaultInjectingSource(ReplaySource(recording, pace="recorded", loop=True), FaultPlan(stall={1: 30.0}))
    with LatestFrameSource(stalled) as latest:
        assert latest.get(timeout=1.0) is not None
        assert latest.get(timeout=0.001) is None
        assert latest.calibration is not None and latest.is_lost is False


# ---------------------------------------------------------------- ZED Mini over UVC (file-fed capture)


class FileCapture:
    """A stand-in for cv2.VideoCapture of a ZED: serves side-by-side BGR frames made from a recording's files.

    `fail_after` reads succeed, then every read fails (a pulled cable) until the capture is reopened.
    """

    def __init__(
        self, frames: list[np.ndarray], opened: bool, fail_after: int | None, native_size: tuple[int, int] | None = None
    ) -> None:
        self.frames, self.opened, self.fail_after = frames, opened, fail_after
        self.native_size = native_size
        self.props: dict[int, float] = {}
        self.reads = 0
        self.released = False

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return self.opened

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        if self.native_size and prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            return float(self.native_size[0 if prop == cv2.CAP_PROP_FRAME_WIDTH else 1])
        return self.props.get(prop, 0.0)

    def read(self) -> tuple[bool, np.ndarray | None]:
        if self.fail_after is not None and self.reads >= self.fail_after:
            return False, None
        frame = self.frames[self.reads % len(self.frames)]
        self.reads += 1
        return True, frame.copy()

    def release(self) -> None:
        self.released = True


class CaptureFactory:
    """Opens FileCaptures: a scripted sequence of (opens?, reads before failing) per open attempt."""

    def __init__(self, frames: list[np.ndarray], script: list[tuple[bool, int | None]], **kwargs: object) -> None:
        self.frames, self.script, self.kwargs = frames, list(script), kwargs
        self.devices: list[int | str] = []
        self.captures: list[FileCapture] = []

    def __call__(self, device: int | str) -> FileCapture:
        self.devices.append(device)
        opened, fail_after = self.script.pop(0) if self.script else (True, None)
        capture = FileCapture(self.frames, opened, fail_after, **self.kwargs)  # type: ignore[arg-type]
        self.captures.append(capture)
        return capture


@pytest.fixture
def vga_frames(tmp_path: Path) -> tuple[list[StereoFrame], list[np.ndarray]]:
    """Three VGA-mode pairs, recorded to files and read back as the side-by-side BGR images a ZED sends."""
    pairs = make_frames(3, size=(672, 376), seed=3)
    with Recorder(tmp_path / "zed") as recorder:
        record(iter(pairs), recorder)
    side_by_side = [
        np.hstack([cv2.imread(str(tmp_path / "zed" / side / f"{i:06d}.png")) for side in ("left", "right")])
        for i in range(3)
    ]
    return pairs, side_by_side


def test_zed_uvc_splits_side_by_side_into_rgb_halves(vga_frames, shared_data: Path) -> None:
    pairs, images = vga_frames
    factory = CaptureFactory(images, [(True, None)])
    conf = shared_data / "calibration" / "zed" / "SN1010.conf"
    with ZedUvcSource("/dev/video4", "VGA", 30, calibration=conf, capture_factory=factory) as source:
        got = [next(source) for _ in range(4)]
        assert source.calibration == from_zed_conf(conf, "VGA")
    capture = factory.captures[0]
    assert factory.devices == ["/dev/video4"]
    assert (capture.props[cv2.CAP_PROP_FRAME_WIDTH], capture.props[cv2.CAP_PROP_FRAME_HEIGHT]) == (1344, 376)
    assert capture.props[cv2.CAP_PROP_FPS] == 30 and capture.released
    for frame, original in zip(got, pairs + pairs[:1]):
        assert _same(frame, original)
    assert [f.index for f in got] == [0, 1, 2, 3]
    assert all(b.timestamp_ns > a.timestamp_ns for a, b in zip(got, got[1:]))


def test_zed_uvc_reconnects_with_exponential_backoff_reporting_lost(vga_frames) -> None:
    pairs, images = vga_frames
    factory = CaptureFactory(images, [(True, 2), (False, None), (False, None), (False, None), (True, None)])
    lost_during_wait: list[bool] = []
    delays: list[float] = []
    source: ZedUvcSource

    def sleep(seconds: float) -> None:
        delays.append(seconds)
        lost_during_wait.append(source.is_lost)

    source = ZedUvcSource(0, "VGA", capture_factory=factory, sleep=sleep, backoff=Backoff(0.1, 2.0, 0.3))
    got = [next(source) for _ in range(3)]
    assert delays == [0.1, 0.2, 0.3, 0.3]  # three failed reopen attempts, then success; capped at 0.3 s
    assert lost_during_wait == [True] * 4
    assert not source.is_lost and source.reconnects == 1
    assert [f.index for f in got] == [0, 1, 2]
    assert _same(got[2], pairs[0])  # the reopened camera starts its stream again
    assert factory.captures[0].released
    source.close()


def test_zed_uvc_without_reconnect_raises_disconnected(vga_frames) -> None:
    _, images = vga_frames
    source = ZedUvcSource(0, "VGA", capture_factory=CaptureFactory(images, [(True, 1)]), reconnect=False)
    next(source)
    with pytest.raises(SourceDisconnected, match="stopped delivering"):
        next(source)
    assert source.is_lost


def test_zed_uvc_rejects_bad_mode_fps_calibration_device_and_foreign_camera(vga_frames, shared_data: Path) -> None:
    _, images = vga_frames
    with pytest.raises(SourceConfigError, match="HD4K.*HD2K, HD1080, HD720, VGA"):
        ZedUvcSource(0, "HD4K", capture_factory=CaptureFactory(images, []))
    with pytest.raises(SourceConfigError, match="fps 60 is not offered in mode HD1080"):
        ZedUvcSource(0, "HD1080", 60, capture_factory=CaptureFactory(images, []))
    with pytest.raises(SourceUnavailable, match="cannot be opened"):
        ZedUvcSource(2, "VGA", capture_factory=CaptureFactory(images, [(False, None)]))
    with pytest.raises(
        CalibrationError, match=r"image_size: is 1280×720 px \(expected 672×376 px, one eye in mode VGA"
    ):
        ZedUvcSource(
            0,
            "VGA",
            calibration=from_zed_conf(shared_data / "calibration" / "zed" / "SN1010.conf", "HD"),
            capture_factory=CaptureFactory(images, []),
        )
    with pytest.raises(SourceConfigError, match=r"delivers 640×480 instead of mode VGA \(1344×376\)"):
        ZedUvcSource(0, "VGA", capture_factory=CaptureFactory(images, [(True, None)], native_size=(640, 480)))


# ---------------------------------------------------------------- specs


@pytest.mark.parametrize(
    "rest, expected",
    [
        ("0", (0, "HD720")),
        ("1:VGA", (1, "VGA")),
        ("/dev/video0", ("/dev/video0", "HD720")),
        ("/dev/video0:hd1080", ("/dev/video0", "HD1080")),
        ("", (0, "HD720")),
    ],
)
def test_zed_spec_parses_device_and_mode(rest: str, expected: tuple[int | str, str]) -> None:
    assert parse_zed_spec(rest) == expected


def test_zed_spec_with_an_unknown_mode_names_the_modes() -> None:
    for rest in ("0:HD4K", "/dev/video0:UHD", "4K"):
        with pytest.raises(SourceConfigError, match=r"mode '.*' is unknown; expected one of HD2K, HD1080, HD720, VGA"):
            parse_zed_spec(rest)
    by_path = "/dev/v4l/by-path/pci-0000:00:14.0-usb-0:1:1.0-video-index0"
    assert parse_zed_spec(by_path) == (by_path, "HD720")
    assert parse_zed_spec(by_path + ":vga") == (by_path, "VGA")


def test_replay_with_a_zed_conf_reads_it_at_the_recording_resolution(
    vga_frames, tmp_path: Path, shared_data: Path
) -> None:
    conf = shared_data / "calibration" / "zed" / "SN1010.conf"
    with open_source(f"replay:{tmp_path / 'zed'}", calibration=conf, pace="fast") as source:
        assert source.frame_size == (672, 376)
        assert source.calibration == from_zed_conf(conf, "VGA")
    _, side_by_side = vga_frames
    video = tmp_path / "zed_sbs.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (1344, 376))
    for image in side_by_side:
        writer.write(image)
    writer.release()
    with open_source(f"replay:{video}", calibration=conf, pace="fast") as source:
        assert source.frame_size == (672, 376) and source.calibration == from_zed_conf(conf, "VGA")
        assert len(list(source)) == 3
    with Recorder(tmp_path / "odd") as recorder:
        record(iter(make_frames(2, size=(100, 60))), recorder)
    with pytest.raises(CalibrationError, match=r"SN1010\.conf: resolution: the frames are 100×60 px .*672×376"):
        open_source(f"replay:{tmp_path / 'odd'}", calibration=conf)


def test_open_source_replay_and_bad_specs(recording: Path, calibration: StereoCalibration, tmp_path: Path) -> None:
    with open_source(f"replay:{recording}", pace="fast") as source:
        assert isinstance(source, ReplaySource)
        assert source.calibration == calibration
        assert len(list(source)) == 6
    other = tmp_path / "other.yaml"
    from camera import write_opencv_file

    write_opencv_file(
        StereoCalibration(
            calibration.K1, calibration.D1, calibration.K2, calibration.D2, calibration.R, np.array([-0.12, 0, 0]), SIZE
        ),
        other,
    )
    with open_source(f"replay:{recording}", calibration=other, pace="fast") as source:
        assert source.calibration == load_calibration(other)
    with open_source(f"replay:{recording}", pace="recorded", latest=True) as source:
        assert isinstance(source, LatestFrameSource) and next(source).index == 0
    for spec, message in [("webcam:0", "expected zed"), ("oak:wide", "oak:WIDTHxHEIGHT"), ("replay:", "replay:PATH")]:
        with pytest.raises(SourceConfigError, match=message):
            open_source(spec)
