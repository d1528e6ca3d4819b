"""The soak's invariant checker (`benchmarks/soak_invariants.py`) fails on each breach it exists for.

Why: a soak that reports "0 breaches" proves something only if its checker fails on a breach. Each test
takes one recording the checker passes and breaks it the way the issue names (issue 39: a stale send,
a leaked file descriptor, a torn middle line) or the way a status could lie; no daemon runs.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from soak_invariants import SAFETY, Fault, Limits, Recording, Sent, Span, Stat, State, check  # noqa: E402

LIMITS = Limits()
HEADER = {"schema": "branchrange/run-header/v1", "kind": "daemon"}


def _line(record: dict) -> str:
    return json.dumps(record)


def calm_recording(seconds: float = 120.0) -> Recording:
    """A daemon started at 0 s: a result with a cut point captured every 0.1 s, a target 0.2 s after each,
    HEARTBEAT ACTIVE each second, flat resources, a truthful /health, a whole log; one 1.5 s stall at
    60 s (no results, no targets, HEARTBEAT CRITICAL from 61 s, targets again 0.3 s after it ends)."""
    rec = Recording(spans=[Span(pid=7, started=0.0)], faults=[Fault("camera.stall", 60.0, 61.5)])
    for tenth in range(int(seconds * 10)):
        at = tenth / 10
        if 60.0 <= at < 61.7:
            continue
        rec.captures.append(at)
        rec.sent.append(Sent(at + 0.2, "target"))
    for second in range(int(seconds)):
        rec.sent.append(Sent(second + 0.05, "lost" if second == 61 else "ok"))
    rec.sent.append(Sent(61.75, "ok"))  # the camera is back: a HEARTBEAT at once
    rec.sent.sort(key=lambda s: s.at)
    rec.stats = [Stat(float(t), 7, 400_000 + (t % 3), 40 + (t % 5 == 0), 30) for t in range(int(seconds))]
    rec.states = [State(float(t), "health", False, True, "world") for t in range(5, int(seconds))]
    rec.log_lines = [_line(HEADER)] + [_line({"t": i / 10}) for i in range(50)]  # results as the soak keeps them
    return rec


def names(rec: Recording) -> list[str]:
    return [breach.invariant for breach in check(rec, LIMITS)]


def test_a_calm_recording_passes():
    assert names(calm_recording()) == []


def test_a_deliberately_stale_send_fails_it():
    rec = calm_recording()
    rec.sent.append(Sent(61.2, "target"))  # during the stall: the newest capture is 1.3 s old
    rec.sent.sort(key=lambda s: s.at)
    breaches = check(rec, LIMITS)
    assert [b.invariant for b in breaches][:1] == ["stale_target"] and breaches[0].at == 61.2


def test_a_target_from_the_previous_daemon_fails_it():
    rec = calm_recording()
    rec.spans = [Span(7, 0.0, 80.0), Span(8, 80.05)]  # restarted: the new daemon logged nothing yet
    rec.captures = [c for c in rec.captures if not 80.0 <= c < 82.0]
    assert "target_from_before_restart" in names(rec)


def test_a_target_while_the_heartbeat_says_camera_lost_fails_it():
    rec = calm_recording()
    rec.sent = [s for s in rec.sent if not (s.kind == "ok" and 61 < s.at < 64)]  # CRITICAL until 64
    rec.sent.sort(key=lambda s: s.at)
    assert "target_while_camera_lost" in names(rec)


def test_a_leaked_file_descriptor_fails_it():
    rec = calm_recording()
    rec.stats = [replace(s, fds=s.fds + (s.at > 70)) for s in rec.stats]  # one more descriptor, never closed
    assert names(rec) == ["fd_leak"]


def test_memory_growing_past_five_percent_fails_it():
    rec = calm_recording()
    rec.stats = [replace(s, rss_kb=int(s.rss_kb * (1 + 0.001 * s.at))) for s in rec.stats]  # ~9 % in 90 s
    assert names(rec) == ["rss_growth"]


def test_a_torn_middle_line_fails_it_but_a_torn_last_line_owned_up_to_by_the_restart_does_not():
    rec = calm_recording()
    rec.log_lines[20] = rec.log_lines[20][:5]
    assert names(rec) == ["torn_line"]
    rec.log_lines.insert(21, _line({**HEADER, "previous_line_torn": True}))  # a restart after a kill says so
    assert names(rec) == []
    rec.log_lines[20] = _line({"t": 1.9})  # ... and claiming a torn line that is whole fails
    assert names(rec) == ["false_torn_claim"]


def test_a_slow_recovery_fails_it():
    rec = calm_recording()
    rec.sent = [s for s in rec.sent if not (61.5 <= s.at < 64.0 and s.kind == "target")]  # first target 2.5 s after
    assert names(rec) == ["slow_recovery"]


def test_a_health_that_says_camera_up_during_a_long_stall_fails_it():
    rec = calm_recording()
    rec.faults = [Fault("camera.stall", 60.0, 64.0)]
    rec.sent = [s for s in rec.sent if not (60.0 <= s.at < 64.2 and s.kind == "target")]
    rec.states = [replace(s, camera_lost=False) for s in rec.states]
    rec.sent = [s for s in rec.sent if s.at != 61.75]
    assert names(rec) == ["health_untrue"] * 3  # at 62, 63 and 64 s; 61 s is within the detection time


def test_a_full_disk_logged_twice_or_stopping_the_targets_fails_it():
    rec = calm_recording()
    rec.faults.append(Fault("disk.full", 80.0, 85.0))
    rec.daemon_log = [(80.1, "results log /x: cannot write (No space left on device)")]
    assert names(rec) == []
    rec.daemon_log.append((82.0, "results log /x: cannot write (No space left on device)"))
    rec.sent = [s for s in rec.sent if not (81.0 <= s.at < 83.5)]  # no frame set for 2.6 s
    assert sorted(names(rec)) == ["disk_full_logged_twice", "output_stopped_by_full_disk"]


def test_results_logged_out_of_capture_order_fail_it_unless_a_reopened_camera_says_so():
    rec = calm_recording()
    rec.log_lines[30], rec.log_lines[31] = rec.log_lines[31], rec.log_lines[30]
    assert names(rec) == ["log_out_of_order"]
    rec = calm_recording()
    rec.log_lines.insert(30, _line({"schema": "branchrange/camera-reopened/v1", "event": "camera_reopened"}))
    rec.log_lines[31:31] = [_line({"t": 0.5})]  # a new opening may go on from lower times
    assert names(rec) == []


def test_a_clock_jump_that_did_not_reach_the_daemon_fails_it():
    rec = calm_recording()
    rec.clock = [(40.0, 3600.0), (90.0, 0.0)]
    rec.wall_skews = [(t, 3600.0 if 40.0 < t < 90.0 else 0.0) for t in range(5, 120)]
    assert names(rec) == []
    rec.wall_skews = [(t, 0.0) for t in range(5, 120)]  # the daemon's Date never moved
    assert names(rec) == ["clock_jump_not_in_force"]  # one breach for the run of readings
    # one reading without the offset among readings with it: the shim's stray read, not a clock that moved
    rec.wall_skews = [(t, 0.0 if t == 60 else 3600.0 if 40.0 < t < 90.0 else 0.0) for t in range(5, 120)]
    assert names(rec) == []
    # two in a row: the jump did not hold
    rec.wall_skews = [(t, 0.0 if t in (60, 61) else 3600.0 if 40.0 < t < 90.0 else 0.0) for t in range(5, 120)]
    assert names(rec) == ["clock_jump_not_in_force"]


def test_a_calm_state_not_back_is_a_slow_recovery_not_a_lie_and_only_lies_are_safety_breaches():
    rec = calm_recording()
    rec.states = [replace(s, mode="camera") if 90 <= s.at < 95 else s for s in rec.states]  # world mode late
    assert names(rec) == ["health_not_back"] * 5
    rec.sent = [s for s in rec.sent if not (61.5 <= s.at < 64.0 and s.kind == "target")]  # slow as well
    rec.sent.append(Sent(61.2, "target"))  # and one stale send
    rec.sent.sort(key=lambda s: s.at)
    gated = [name for name in names(rec) if name in SAFETY]
    assert gated == ["stale_target", "target_while_camera_lost"]
    assert {"slow_recovery", "health_not_back"} <= set(names(rec))


def test_a_daemons_start_is_judged_from_its_first_heartbeat_and_a_mute_one_from_its_process_start():
    # seed 11 at load 6: the interpreter, the imports, the camera and the model took 3.1 s before the first
    # HEARTBEAT, the 3 fused results of the hand-over 2 s more; /health said camera mode at 4 and 5 s, which
    # the first daemon's start was judged for from its process start (3.5 s), a restarted one's from its
    # first HEARTBEAT
    rec = calm_recording()
    rec.sent = [s for s in rec.sent if s.at >= 3.1] + [Sent(3.1, "ok")]
    rec.sent.sort(key=lambda s: s.at)
    rec.states = [State(float(t), "health", False, True, "camera" if t < 6 else "world") for t in range(4, 120)]
    assert names(rec) == []
    rec.states.append(State(6.7, "health", False, True, "camera"))  # 3.6 s after it was up: still not back
    assert names(rec) == ["health_not_back"]
    rec.sent = [s for s in rec.sent if s.kind not in ("ok", "lost")]  # a daemon that never sent a HEARTBEAT
    rec.states.pop()
    assert names(rec) == ["health_not_back"] * 2  # at 4 and 5 s: judged from its process start


def test_the_log_tail_follows_the_daemons_rotation_without_tearing_a_line(tmp_path):
    """The 43-minute soak of 2026-11-29 read the new file at the old file's offset after a rotation: torn
    lines, and every later capture missed (thousands of stale targets that were not)."""
    import threading

    from soak import LogTail

    path = tmp_path / "results.jsonl"

    def line(i: int) -> str:
        return json.dumps({"frame": {"timestamp_ns": i * 10**9}, "branches": [{"id": 1}]}) + "\n"

    path.write_text(line(1) + line(2))
    tail, rec, lock = LogTail(path), Recording(), threading.Lock()
    tail.read(rec, lock)
    path.write_text(path.read_text() + line(3))  # written after the read, then the file rotates
    path.rename(tmp_path / "results.jsonl.1")
    path.write_text(line(4))
    tail.read(rec, lock)
    assert rec.captures == [1.0, 2.0, 3.0, 4.0]
    assert all(json.loads(raw) for raw in rec.log_lines)  # every line whole
