"""Paced replays keep their schedule: late frames dropped and counted, decoding ahead of the slot, a start
time and a start signal (file, UDP on 127.0.0.1) for a simulator kept in step."""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from camera.sources import LatestFrameSource, Recorder, ReplaySource, SourceConfigError, StereoFrame, open_source
from camera.sources.clock_sync import START_SCHEMA, ClockSync, parse_start_at, parse_start_signal

PERIOD_NS = 40_000_000
T0 = 7_000_000_000
COUNT = 6
MS = 1_000_000


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    """Six small pairs 40 ms apart, each with a mask whose value is its index + 1."""
    rng = np.random.default_rng(3)
    out = tmp_path / "rec"
    with Recorder(out, source_spec="test:frames") as recorder:
        for i in range(COUNT):
            left, right = (rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for _ in range(2))
            recorder.write(StereoFrame(left, right, T0 + i * PERIOD_NS, i, np.full((24, 32), i + 1, np.uint8)))
    return out


class FakeTime:
    """A monotonic clock that moves only when the replay waits, a frame decodes or the consumer works."""

    def __init__(self, source: ReplaySource, decode_ns: dict[int, int] | None = None, oversleep_ns: int = 0) -> None:
        self.now = 0
        self.decode_ns, self.oversleep_ns = decode_ns or {}, oversleep_ns
        source._clock = self.clock
        source._stop.wait = self.wait  # type: ignore[method-assign]
        read = source._frames.read
        reads = iter(range(10**6))

        def slow_read() -> StereoFrame | None:
            self.now += self.decode_ns.get(next(reads), 0)
            return read()

        source._frames.read = slow_read  # type: ignore[method-assign]

    def clock(self) -> int:
        return self.now

    def wait(self, seconds: float) -> bool:
        self.now += round(seconds * 1e9) + self.oversleep_ns
        return False


def test_a_slow_consumer_gets_the_frames_still_on_time_and_the_late_ones_are_counted(recording: Path) -> None:
    source = ReplaySource(recording, pace="recorded")
    fake = FakeTime(source)
    released = []
    for frame in source:
        released.append((frame.index, frame.timestamp_ns, fake.now))
        fake.now += 100 * MS  # the consumer works 100 ms per frame
    # frame 1 (due at 40 ms) is 60 ms late: dropped; frame 2 (80 ms) is 20 ms late, just within the limit
    assert released == [(0, T0, 0), (2, T0 + 2 * PERIOD_NS, 100 * MS), (5, T0 + 5 * PERIOD_NS, 200 * MS)]
    assert source.dropped_late == 3  # 1, 3 and 4: recorded indices and stamps show the gaps
    assert source.late_limit_ns == 20 * MS  # half the 40 ms period


def test_a_tighter_late_limit_drops_what_half_a_period_would_release(recording: Path) -> None:
    source = ReplaySource(recording, pace="recorded", max_late_ms=10)
    fake = FakeTime(source)
    released = []
    for frame in source:
        released.append(frame.index)
        fake.now += 100 * MS  # frame 2 would come 20 ms after its slot: more than 10 ms
    assert released == [0, 3] and source.dropped_late == 4 and source.late_limit_ns == 10 * MS  # 5: 20 ms late
    with pytest.raises(SourceConfigError, match="max_late_ms is 0"):
        ReplaySource(recording, max_late_ms=0)


def test_a_scheduler_that_wakes_the_replay_late_is_allowed_for(recording: Path) -> None:
    source = ReplaySource(recording, pace="recorded")
    fake = FakeTime(source, oversleep_ns=10 * MS)  # every wait returns 10 ms late
    released = [fake.now for _ in source]
    # the first wait overslept; from then on the replay wakes 10 ms early and releases on the slot
    assert released == [0, 50 * MS, 80 * MS, 120 * MS, 160 * MS, 200 * MS] and source.dropped_late == 0


def test_a_frame_the_scheduler_wakes_too_late_is_never_released_late(recording: Path) -> None:
    source = ReplaySource(recording, pace="recorded")
    FakeTime(source, oversleep_ns=30 * MS)  # every wait returns 30 ms late: past the 20 ms limit
    assert [frame.index for frame in source] == [0] and source.dropped_late == COUNT - 1


def test_decoding_starts_ahead_of_the_slot_so_the_frame_is_ready_at_it(recording: Path) -> None:
    source = ReplaySource(recording, pace="recorded")
    fake = FakeTime(source, decode_ns={i: 15 * MS for i in range(COUNT)})
    released = [(frame.index, fake.now) for frame in source]
    start = released[0][1]  # the first frame decodes before the schedule starts
    assert [(index, t - start) for index, t in released] == [(i, i * PERIOD_NS) for i in range(COUNT)]
    assert source.dropped_late == 0


def test_a_frame_whose_decode_overruns_is_dropped_after_decoding(recording: Path) -> None:
    source = ReplaySource(recording, pace="recorded")
    fake = FakeTime(source, decode_ns={2: 35 * MS})  # the third read takes 35 ms: 15 ms past the 20 ms limit
    indices = [frame.index for frame in source]
    assert indices == [0, 1, 3, 4, 5] and source.dropped_late == 1
    assert fake.now == 5 * PERIOD_NS  # the last frame still at its slot


def test_fast_pace_and_loops_drop_nothing(recording: Path) -> None:
    source = ReplaySource(recording, pace="fast", loop=True)
    FakeTime(source, decode_ns={i: 100 * MS for i in range(20)})
    assert [next(source).index for _ in range(8)] == [0, 1, 2, 3, 4, 5, 6, 7]
    assert source.dropped_late == 0
    source.close()


def test_a_paced_loop_keeps_its_schedule_across_the_seam(recording: Path) -> None:
    source = ReplaySource(recording, pace="recorded", loop=True, start=4)
    fake = FakeTime(source)
    released = [(frame.index, frame.timestamp_ns - T0, fake.now) for frame in (next(source) for _ in range(4))]
    source.close()
    assert released == [
        (4, 4 * PERIOD_NS, 0),
        (5, 5 * PERIOD_NS, PERIOD_NS),
        (10, 6 * PERIOD_NS, 2 * PERIOD_NS),
        (11, 7 * PERIOD_NS, 3 * PERIOD_NS),
    ]


def test_ignore_masks_leaves_the_masks_unread(recording: Path) -> None:
    assert [int(f.mask[0, 0]) for f in ReplaySource(recording, pace="fast")] == list(range(1, COUNT + 1))
    assert all(f.mask is None for f in ReplaySource(recording, pace="fast", ignore_masks=True))
    with open_source(f"replay:{recording}?ignore_masks=true", pace="fast") as source:
        assert next(source).mask is None


def test_the_start_datagram_arrives_on_loopback_with_the_start_instant(recording: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.settimeout(5)
        port = listener.getsockname()[1]
        before_wall, before_mono = time.time_ns(), time.monotonic_ns()
        with open_source(f"replay:{recording}?start_signal=udp:127.0.0.1:{port}", pace="recorded") as source:
            first = next(source)
            after_wall, after_mono = time.time_ns(), time.monotonic_ns()
            start = json.loads(listener.recv(65536))
    assert start["schema"] == START_SCHEMA and start["source"] == str(recording)
    assert (start["first_timestamp_ns"], start["first_index"]) == (first.timestamp_ns, first.index) == (T0, 0)
    assert before_wall <= start["wall_ns"] <= after_wall and before_mono <= start["monotonic_ns"] <= after_mono


def test_a_start_time_delays_the_first_frame_and_the_start_file_says_when(recording: Path, tmp_path: Path) -> None:
    signal = tmp_path / "start.json"
    started = time.monotonic()
    sync = ClockSync.parse(str(time.time() + 0.3), [f"file:{signal}"])
    with ReplaySource(recording, pace="recorded", clock_sync=sync) as source:
        next(source)
        waited = time.monotonic() - started
    start = json.loads(signal.read_text())
    assert waited >= 0.25
    assert start["wall_ns"] / 1e9 >= sync.start_at_s and start["first_index"] == 0
    assert not list(tmp_path.glob(".start.json.*"))  # written through a temporary file, renamed


def test_the_daemon_sees_the_replays_late_drops(recording: Path) -> None:
    inner = ReplaySource(recording, pace="recorded")
    fake = FakeTime(inner, decode_ns={1: 30 * MS})
    with LatestFrameSource(inner) as latest:
        for _ in latest:
            pass
    assert inner.dropped_late == 1 and latest.dropped_late == 1 and fake.now >= 5 * PERIOD_NS


@pytest.mark.parametrize(
    "text, seconds",
    [
        ("1764353400", 1764353400.0),
        ("1764353400.25", 1764353400.25),
        ("2025-11-28T18:10:00Z", 1764353400.0),
        ("2025-11-28T19:10:00+01:00", 1764353400.0),
    ],
)
def test_start_times_in_unix_seconds_or_iso_with_an_offset(text: str, seconds: float) -> None:
    assert parse_start_at(text) == seconds


def test_a_start_time_with_a_plus_offset_survives_the_spec(recording: Path) -> None:
    spec = f"replay:{recording}?start_at=2025-11-28T19:10:00+01:00"
    with open_source(spec, pace="fast") as source:
        assert isinstance(source, ReplaySource) and source.clock_sync is not None
        assert source.clock_sync.start_at_s == 1764353400.0


@pytest.mark.parametrize(
    "call, expected",
    [
        (lambda: parse_start_at("2025-11-28T18:10:00"), "with a UTC offset"),
        (lambda: parse_start_at("tomorrow"), "expected Unix seconds"),
        (lambda: parse_start_signal("tcp:127.0.0.1:9"), "expected file:PATH or udp:HOST:PORT"),
        (lambda: parse_start_signal("udp:127.0.0.1:99999"), "expected file:PATH or udp:HOST:PORT"),
        (lambda: parse_start_signal("udp:no-such-host.invalid:9500"), "is unknown"),
        (lambda: parse_start_signal("file:/no/such/folder/start.json"), "does not exist"),
    ],
)
def test_bad_clock_sync_values_say_what_is_expected(call, expected: str) -> None:
    with pytest.raises(SourceConfigError, match=expected):
        call()


def test_bad_replay_spec_options_are_named(recording: Path) -> None:
    with pytest.raises(SourceConfigError, match="option 'startat' is unknown"):
        open_source(f"replay:{recording}?startat=1")
    with pytest.raises(SourceConfigError, match="ignore_masks is 'yes'"):
        open_source(f"replay:{recording}?ignore_masks=yes")
    with pytest.raises(SourceConfigError, match="give it once"):
        open_source(f"replay:{recording}?start_at=1", clock_sync=ClockSync(start_at_s=2.0))
    with pytest.raises(SourceConfigError, match="max_late_ms is 'soon'"):
        open_source(f"replay:{recording}?max_late_ms=soon")
    with pytest.raises(SourceConfigError, match="max_late_ms given in the spec and as an option"):
        open_source(f"replay:{recording}?max_late_ms=5", max_late_ms=10)
    with pytest.raises(SourceConfigError, match="start_at may be given once"):
        open_source(f"replay:{recording}?start_at=1&start_at=2")


def test_the_late_limit_comes_from_the_spec_or_the_argument(recording: Path) -> None:
    with open_source(f"replay:{recording}?max_late_ms=5", pace="recorded") as source:
        assert isinstance(source, ReplaySource) and source.late_limit_ns == 5 * MS
    with open_source(f"replay:{recording}", pace="recorded", max_late_ms=7.5) as source:
        assert isinstance(source, ReplaySource) and source.late_limit_ns == 7_500_000


def test_a_replay_closed_while_waiting_for_its_start_time_announces_nothing(recording: Path, tmp_path: Path) -> None:
    signal = tmp_path / "start.json"
    source = ReplaySource(recording, clock_sync=ClockSync.parse(str(time.time() + 60), [f"file:{signal}"]))
    threading.Timer(0.2, source.close).start()
    started = time.monotonic()
    with pytest.raises(StopIteration):
        next(source)
    assert time.monotonic() - started < 10 and not signal.exists()
