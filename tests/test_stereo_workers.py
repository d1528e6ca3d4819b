"""The daemon's stereo stage in worker processes (`stereo.workers`): capture order, stale results, dead workers."""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import signal
import threading
import time

import numpy as np
import pytest
from api_scene import BASELINE_M, FOCAL_PX, bar_scene
from mavlink_peer import LoopbackPeer, of_type
from stereo_worker_cases import slowed_pipeline

from branchrange.config.loader import Config, pipeline_for
from branchrange.config.sections import CameraConfig, MavlinkConfig
from branchrange.core.frame_results import process_frame
from branchrange.core.pipeline import StereoConfig
from branchrange.core.roi import RoiConfig
from branchrange.onboard.daemon import Daemon
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay
from branchrange.onboard.shm_transport import ShmReader, ShmWriter
from branchrange.onboard.stereo_workers import StereoWorkers, worker_count
from camera.calibration import from_rectified
from camera.sources import FaultInjectingSource, FaultPlan, Recorder, ReplaySource, StereoFrame

FRAMES = 8
PERIOD_NS = 250_000_000  # 4 fps
CALIBRATION = from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (320, 256))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """An 8-frame 4 fps recording of the bar scene, each frame's right view shifted a little more (distinct
    disparities, so a result of one frame never equals another's)."""
    scene = bar_scene()
    out = tmp_path_factory.mktemp("rec") / "bar"
    with Recorder(out, calibration=CALIBRATION, source_spec="synthetic bar") as rec:
        for i in range(FRAMES):
            right = np.roll(scene.right, -(i % 3), axis=1)
            rec.write(StereoFrame(scene.left, right, 1_000_000_000 + i * PERIOD_NS, i))
    return out


def config(recording, workers: int, max_age_s: float = 30.0, **mavlink) -> Config:
    return Config(
        camera=CameraConfig(source=f"replay:{recording}"),
        stereo=StereoConfig(max_disp=64, workers=workers),
        mavlink=MavlinkConfig(max_result_age_s=max_age_s, **mavlink),
    )


class Errors:
    """A `DaemonMetrics` that keeps the errors counted."""

    def __init__(self) -> None:
        self.kinds: list[str] = []

    def observe_frame(self, seconds: float, source: str) -> None:
        pass

    def count_error(self, kind: str) -> None:
        self.kinds.append(kind)


def run_daemon(cfg: Config, recording, factory, relay=None, during=None, metrics=None) -> tuple[Daemon, list]:
    """Replay the recording at its own pace through a daemon with `factory`'s workers; its published results.
    `during(daemon)`, when given, runs in another thread while the daemon does."""
    published: list = []
    daemon = Daemon(
        cfg,
        open_source=lambda: ReplaySource(recording, pace="recorded"),
        pipeline=pipeline_for(cfg, CALIBRATION),
        relay=relay,
        metrics=metrics,
        observers=[lambda result, _: published.append(result)],
        pipeline_factory=factory,
    )
    helper = threading.Thread(target=during, args=(daemon,), daemon=True) if during else None
    try:
        if helper is not None:
            helper.start()
        daemon.run()
    finally:
        daemon.close()
    if helper is not None:
        helper.join(timeout=30)
    return daemon, published


def without_times(result) -> dict:
    """A result as JSON without what depends on the machine's speed (timings, latency)."""
    record = result.to_json_dict()
    for key in ("timing_ms", "latency", "freshness"):
        record.pop(key, None)
    return record


def same_as_one_thread(published, recording) -> None:
    """Each published result equals the one a single pipeline gives those frames in that order (tracking
    included): what the daemon did before it had workers."""
    frames = {frame.index: frame for frame in ReplaySource(recording, pace="fast")}
    cfg = config(recording, 1)
    pipeline = pipeline_for(cfg, CALIBRATION)
    for result in published:
        assert without_times(result) == without_times(process_frame(pipeline, frames[result.frame.index]))


def test_worker_count_comes_from_the_usable_cores_when_zero():
    assert worker_count(0) == len(os.sched_getaffinity(0))
    assert worker_count(3) == 3 and worker_count(1) == 1


def test_shared_memory_transport_round_trip_grows_its_block():
    writer, reader = ShmWriter(), ShmReader()
    try:
        for size in (64, 256):  # the second frame does not fit the first block
            frame = StereoFrame(
                np.full((size, size, 3), 7, np.uint8),
                np.arange(size * size * 3, dtype=np.uint8).reshape(size, size, 3),
                5,
                2,
            )
            packed = writer.pack(frame)
            assert packed.block is not None and len(packed.data) < 1024  # the pixels are not in the pickle
            back = reader.unpack(packed)
            assert np.array_equal(back.left, frame.left) and np.array_equal(back.right, frame.right)
            assert (back.timestamp_ns, back.index, back.mask) == (5, 2, None)
    finally:
        writer.close()
        reader.close()


def test_one_worker_runs_in_the_daemon_thread_and_keeps_todays_results(recording):
    daemon, published = run_daemon(config(recording, 1), recording, factory=None)
    assert daemon.health()["stereo_workers"] == {"count": 1, "restarts": 0, "lost_frames": 0}
    assert published
    same_as_one_thread(published, recording)


def test_outputs_are_handed_on_in_capture_order_when_a_later_frame_finishes_first(recording):
    """Frame 0 takes 1.5 s in its worker, frame 1 none: frame 1 is done first, yet handed on after frame 0."""
    cfg = config(recording, 2)
    frames = list(ReplaySource(recording, pace="fast"))[:3]
    outputs: list = []
    factory = functools.partial(slowed_pipeline, cfg, CALIBRATION, {0: 1.5})
    pool = StereoWorkers(2, factory, outputs.append)
    try:
        pool.wait_ready(threading.Event())
        for frame in frames:
            pool.wait_free(threading.Event())
            pool.submit(frame, time.monotonic(), 0)
        pool.wait_idle()
    finally:
        pool.close()
    assert [output.index for output in outputs] == [0, 1, 2]
    assert outputs[1].done_at < outputs[0].done_at  # finished first, handed on second
    assert all(output.stage is not None and output.error is None for output in outputs)
    pipeline = pipeline_for(cfg, CALIBRATION)
    for frame, output in zip(frames, outputs):  # each worker ran the stereo half and the cut points
        here = pipeline.cut_point_stage(pipeline.stereo_stage(frame.left, frame.right, None, frame.index))
        assert np.array_equal(output.stage.stage.disparity, here.stage.disparity)
        assert output.stage.reason == here.reason and output.stage.valid_share == here.valid_share
        assert output.started_at <= output.halfway_at <= output.done_at


def test_workers_publish_in_capture_order_with_todays_results(recording, caplog):
    """Through the daemon, two workers: results in capture order, each equal to what one thread gives those frames."""
    caplog.set_level(logging.INFO, logger="branchrange.daemon")
    cfg = config(recording, 2)
    daemon, published = run_daemon(cfg, recording, functools.partial(pipeline_for, cfg, CALIBRATION))
    indices = [result.frame.index for result in published]
    assert len(indices) >= 2 and indices == sorted(set(indices))
    assert daemon.health()["stereo_workers"] == {"count": 2, "restarts": 0, "lost_frames": 0}
    assert "stereo stage in 2 worker processes" in caplog.text
    same_as_one_thread(published, recording)


def test_a_result_older_than_max_result_age_is_never_a_target(recording):
    """Each frame takes 0.6 s in its worker, more than `max_result_age_s` = 0.4: every result is late,
    none goes to the autopilot as a target, and /latest calls it stale."""
    peer = LoopbackPeer()
    cfg = config(recording, 2, max_age_s=0.4, url=f"udpout:127.0.0.1:{peer.port}")
    relay = MavlinkRelay(cfg.mavlink, CameraMount.from_rpy())
    factory = functools.partial(slowed_pipeline, cfg, CALIBRATION, {}, 0.6)
    try:
        daemon, published = run_daemon(cfg, recording, factory, relay=relay)
        got = peer.collect(0.3)
    finally:
        peer.close()
    assert published and daemon.late == len(published)
    assert all(r.latency.capture_to_publish_ms > 400 for r in published)
    dists = of_type(got, "DISTANCE_SENSOR")
    assert dists and all(d.msg.current_distance == 1001 for d in dists)  # "no target", never a stale one
    latest = daemon.latest_result()
    assert latest is not None and latest.freshness.stale


def test_a_killed_worker_is_started_again_and_its_frame_counted_as_dropped(recording, caplog):
    caplog.set_level(logging.WARNING, logger="branchrange.daemon")
    cfg = config(recording, 2)
    factory = functools.partial(slowed_pipeline, cfg, CALIBRATION, {}, 0.8)
    killed: list[int] = []

    def kill_one(daemon: Daemon) -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not killed:
            pool = daemon._pool
            busy = [] if pool is None else pool.busy_pids()
            if busy:
                os.kill(busy[0], signal.SIGKILL)
                killed.append(busy[0])
            time.sleep(0.02)

    errors = Errors()
    daemon, published = run_daemon(cfg, recording, factory, during=kill_one, metrics=errors)
    assert killed
    workers = daemon.health()["stereo_workers"]
    assert workers == {"count": 2, "restarts": 1, "lost_frames": 1}
    assert killed[0] not in daemon._pool.pids()  # its slot holds a fresh process
    camera = daemon.health()["camera"]
    assert camera["dropped"] == daemon.dropped >= 1
    indices = [result.frame.index for result in published]
    assert indices == sorted(set(indices))
    # every frame of the recording is accounted for: published, dropped (the dead worker's included), or skipped
    assert len(published) + daemon.dropped + daemon.dropped_late + daemon.skipped + daemon.rejected == FRAMES
    died = [r.getMessage() for r in caplog.records if "died" in r.getMessage()]
    assert len(died) == 1 and f"pid {killed[0]}" in died[0] and "counts as dropped" in died[0]
    assert errors.kinds.count("stereo_worker_lost") == 1  # and in /metrics' error counts


def test_workers_survive_a_dropped_a_corrupt_frame_and_an_unplugged_camera(recording):
    """The camera faults of `test_daemon`'s single-thread case, with two workers: a frame dropped, one corrupt,
    the camera gone for 2 s (HEARTBEAT CRITICAL, reopened, back at frame 6); results stay in capture order and the
    status is back to camera up at the end."""
    peer = LoopbackPeer()
    cfg = config(recording, 2, url=f"udpout:127.0.0.1:{peer.port}")
    cfg = dataclasses.replace(cfg, camera=CameraConfig(source=f"replay:{recording}", stall_timeout_s=0.3))
    opened: list = []

    def open_source():
        plan = FaultPlan(drop={2}, corrupt={4}, disconnect={5: 2.0})
        opened.append(
            FaultInjectingSource(ReplaySource(recording), plan) if not opened else ReplaySource(recording, start=6)
        )
        return opened[-1]

    published: list = []
    daemon = Daemon(
        cfg,
        open_source=open_source,
        pipeline=pipeline_for(cfg, CALIBRATION),
        relay=MavlinkRelay(cfg.mavlink, CameraMount.from_rpy()),
        observers=[lambda result, _: published.append(result)],
        pipeline_factory=functools.partial(pipeline_for, cfg, CALIBRATION),
    )
    try:
        daemon.run()
        got = peer.collect(0.3)
    finally:
        daemon.close()
        peer.close()
    assert daemon.corrupt == 1 and daemon.reopens == 1 and len(opened) == 2
    indices = [result.frame.index for result in published]
    assert indices == sorted(set(indices)) and set(indices) <= {0, 1, 3, 6, 7} and indices[-1] == FRAMES - 1
    statuses = [h.msg.system_status for h in of_type(got, "HEARTBEAT")]
    assert 5 in statuses and statuses[-1] == 4, statuses  # CRITICAL while the camera was gone, ACTIVE after
    health = daemon.health()
    assert health["camera"]["lost"] is False and health["stereo_workers"]["lost_frames"] == 0


def test_keyframes_keep_the_stereo_stage_in_one_thread(recording, caplog):
    caplog.set_level(logging.WARNING, logger="branchrange.daemon")
    cfg = Config(
        camera=CameraConfig(source=f"replay:{recording}"),
        stereo=StereoConfig(max_disp=64, workers=4),
        roi=RoiConfig(keyframe_interval_s=0.5),
    )
    daemon = Daemon(cfg, open_source=lambda: ReplaySource(recording), pipeline=pipeline_for(cfg, CALIBRATION))
    assert daemon.workers == 1
    assert "stereo.workers = 4 ignored" in caplog.text


def test_workers_without_a_pipeline_factory_are_refused(recording):
    cfg = config(recording, 2)
    with pytest.raises(ValueError, match="pipeline_factory"):
        Daemon(cfg, open_source=lambda: ReplaySource(recording), pipeline=pipeline_for(cfg, CALIBRATION))
