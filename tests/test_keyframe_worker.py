"""The keyframes' segmenter in its own worker: the stereo thread never waits for it, its keyframes (for an
older frame) are carried to the newest one, and a crash is logged, restarted and never reported as fresh."""

from __future__ import annotations

import logging
import threading
from dataclasses import replace

import numpy as np
from synth_recording import tree_scene
from test_keyframes import PERIOD_NS, _pipeline, moved, textured

from branchrange.core.keyframe_worker import Keyframe, KeyframeWorker, global_shift
from branchrange.core.masks import BranchMasks


def _keyframe(left: np.ndarray, right: np.ndarray, timestamp_ns: int) -> Keyframe:
    return Keyframe(left[..., 0].copy(), BranchMasks(np.zeros(left.shape[:2], np.int32)), {}, timestamp_ns)


def _pair() -> tuple[np.ndarray, np.ndarray]:
    image = np.dstack([textured()] * 3)
    return image, image


def test_a_crashed_worker_is_logged_and_restarted(caplog):
    calls = []

    def crashes_once(left, right, timestamp_ns):
        calls.append(timestamp_ns)
        if len(calls) == 1:
            raise RuntimeError("segmenter blew up")
        return _keyframe(left, right, timestamp_ns)

    worker = KeyframeWorker(crashes_once)
    left, right = _pair()
    with caplog.at_level(logging.WARNING, logger="branchrange.core.keyframe_worker"):
        assert worker.submit(left, right, 1)
        assert worker.take(wait_s=5.0) is None  # the keyframe was lost with the crash
        assert worker.failures == 1 and "segmenter blew up" in (worker.last_error or "")
        assert worker.submit(left, right, 2)  # a new thread
        done = worker.take(wait_s=5.0)
    worker.close()
    assert done is not None and done.timestamp_ns == 2 and worker.restarts == 1
    messages = [r.getMessage() for r in caplog.records]
    assert any("keyframe worker failed" in m and "segmenter blew up" in m for m in messages)
    assert any("keyframe worker restarted" in m for m in messages)


def test_a_busy_worker_takes_no_second_frame_and_a_reset_drops_its_keyframe():
    release = threading.Event()

    def slow(left, right, timestamp_ns):
        release.wait(5.0)
        return _keyframe(left, right, timestamp_ns)

    worker = KeyframeWorker(slow)
    left, right = _pair()
    assert worker.submit(left, right, 1) and worker.busy
    assert not worker.submit(left, right, 2)
    worker.forget()  # a new sequence while the keyframe is in flight
    release.set()
    assert worker.take(wait_s=5.0) is None
    assert not worker.busy
    worker.close()


def test_the_global_shift_is_the_image_motion():
    for shape in ((180, 320), (360, 640)):
        grey = textured(shape=shape)
        du, dv = global_shift(grey, moved(grey, 12, -8))
        assert abs(du - 12) <= 1.0 and abs(dv + 8) <= 1.0, (shape, du, dv)


def _worker_pipeline(interval_s: float = 0.2, max_age_s: float = 1.0):
    pipeline = _pipeline(interval_s)
    roi = replace(pipeline.config.roi, keyframe_worker=True, track_max_age_s=max_age_s)
    pipeline.config = replace(pipeline.config, roi=roi)
    return pipeline


def test_the_stereo_thread_tracks_on_while_the_worker_computes_and_takes_its_keyframe_when_done():
    scene = tree_scene()
    pipeline = _worker_pipeline()
    release = threading.Event()
    real = pipeline._keyframe

    def held(left, right, timestamp_ns):
        release.wait(10.0)
        return real(left, right, timestamp_ns)

    pipeline.keyframe_worker = KeyframeWorker(held)
    results = []
    for i in range(8):  # 0.47 s: keyframes are due from 0.2 s on, the worker is held
        left, right = moved(scene.left, 2 * i, 0), moved(scene.right, 2 * i, 0)
        results.append(pipeline.process(left, right, None, i, 1_000_000_000 + i * PERIOD_NS))
    assert results[0].origin == "keyframe"
    assert all(r.origin == "tracked" and r.branches for r in results[1:])  # never waited for the worker
    assert pipeline.keyframe_worker.busy
    release.set()
    for _ in range(300):  # let it finish; the next frame takes its keyframe over
        if not pipeline.keyframe_worker.busy:
            break
        threading.Event().wait(0.1)
    left, right = moved(scene.left, 16, 0), moved(scene.right, 16, 0)
    after = pipeline.process(left, right, None, 8, 1_000_000_000 + 8 * PERIOD_NS)
    assert after.origin == "tracked" and after.branches
    assert after.keyframe_age_s < results[-1].keyframe_age_s  # carried from the newer keyframe
    pipeline.keyframe_worker.close()


def test_while_the_worker_is_down_tracks_age_out_and_are_never_reported_older(caplog):
    scene = tree_scene()
    pipeline = _worker_pipeline(interval_s=0.1, max_age_s=0.4)
    real = pipeline._keyframe
    failing = {"on": True}

    def crashing(left, right, timestamp_ns):
        if failing["on"]:
            raise RuntimeError("worker process died")
        return real(left, right, timestamp_ns)

    pipeline.keyframe_worker = KeyframeWorker(crashing)
    results = []
    with caplog.at_level(logging.WARNING, logger="branchrange.core.keyframe_worker"):
        for i in range(16):
            if i == 9:
                failing["on"] = False
            left, right = moved(scene.left, i, 0), moved(scene.right, i, 0)
            results.append(pipeline.process(left, right, None, i, 1_000_000_000 + i * PERIOD_NS))
            if pipeline.keyframe_worker.busy:
                pipeline.keyframe_worker.take(wait_s=0.0)
    assert pipeline.keyframe_worker.failures >= 1 and pipeline.keyframe_worker.restarts >= 1
    assert all(r.keyframe_age_s is not None and r.keyframe_age_s < 0.4 for r in results)
    assert any("keyframe worker failed" in r.getMessage() for r in caplog.records)
    pipeline.keyframe_worker.close()
