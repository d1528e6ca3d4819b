"""The soak's invariants (issue 39 item 2) as pure functions over what a soak recorded.

Every time is `time.monotonic()` seconds of the machine (one clock for the soak, its autopilot
simulator and the daemon's camera, whose frames carry their capture time in `timestamp_ns`).
What is recorded (`Recording`):
- `sent`: what the autopilot received from the daemon, in order: a frame set with or without a
  target (DEBUG_VECT "CUT" finite or NaN), and the daemon's HEARTBEATs (CRITICAL: camera lost);
- `captures`: the capture times of the results the daemon logged that held at least one cut point;
- `spans`: each daemon process, from its start to its end (None while it runs);
- `faults`: the injected faults, each with when it began and ended (a restart ends when the new
  daemon's first HEARTBEAT arrives);
- `stats`: the daemon's RSS, open file descriptors and threads, sampled;
- `states`: what /health and /metrics said (camera lost, link connected, pose mode), sampled;
- `log_lines`: every line of the results log, oldest file first; `daemon_log`: the daemon's own log
  lines with when they arrived (the disk-full message is counted there);
- `blind`: windows in which the results log cannot back a send (the disk is full: results are sent,
  not logged), whose targets are not checked against captures;
- `clock`: each wall-clock jump injected into the daemon (when, and the offset from the real wall
  clock from then on, s); `wall_skews`: the daemon's wall clock as its HTTP `Date` header showed it,
  minus the real one (s), sampled — the proof a jump reached the daemon.

Every result line of the results log is kept in `log_lines` as `{"t": capture time}` (the soak's
reader shortens them), so their order can be judged: within one camera opening (between run headers
and camera-reopened markers) capture times only increase, whatever the wall clock did.

How a stale target is seen from outside: a target may only go out while the cut point it comes from
was captured within `max_result_age_s`, so when a target arrives at `t`, the daemon now running must
have logged a result with a cut point captured in [t − max_result_age_s − slack, t] since it started
(`slack_s`: the camera → daemon hand-over and the loopback delivery, a few ms). That is necessary, not
sufficient (the fused target may come from another branch than the newest result's), and it catches
what matters: a send after results stopped (stall, a killed stereo stage), a send from before a
restart, a frozen frame sent as new. `check` gives every breach, earliest first.
"""

from __future__ import annotations

import bisect
import json
import math
import statistics
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

#: Fault kinds whose recovery is measured from a new daemon (3 s allowed instead of 2 s).
RESTARTS = frozenset({"process.sigterm", "process.sigkill"})
#: The daemon's log message of a results log that cannot be written (`branchrange.onboard.results_log`).
DISK_FULL_MESSAGE = "cannot write"


@dataclass(frozen=True)
class Fault:
    """One injected fault: `kind` ("camera.stall", "mavlink.silence", …) from `start` to `end` (s)."""

    kind: str
    start: float
    end: float


@dataclass(frozen=True)
class Sent:
    """One thing the autopilot received at `at`: "target", "no_target", or a HEARTBEAT "lost" / "ok"."""

    at: float
    kind: str


@dataclass(frozen=True)
class Span:
    """One daemon process: started at `started`, ended at `ended` (None: still running)."""

    pid: int
    started: float
    ended: float | None = None

    def holds(self, at: float) -> bool:
        return self.started <= at and (self.ended is None or at <= self.ended)


@dataclass(frozen=True)
class Stat:
    """The daemon process `pid` at `at`: resident memory (kB), open file descriptors, threads."""

    at: float
    pid: int
    rss_kb: int
    fds: int
    threads: int


@dataclass(frozen=True)
class State:
    """What an endpoint ("health" or "metrics") said at `at`: camera lost, link connected, pose mode."""

    at: float
    endpoint: str
    camera_lost: bool
    link_connected: bool
    mode: str


@dataclass(frozen=True)
class Breach:
    """An invariant broken at `at` (monotonic s; 0 when the evidence has no time), with the evidence."""

    invariant: str
    at: float
    detail: str


@dataclass(frozen=True)
class Limits:
    """The configuration the invariants are judged by (seconds unless named)."""

    max_result_age_s: float = 0.5
    slack_s: float = 0.05
    recovery_s: float = 2.0
    restart_recovery_s: float = 3.0
    stall_timeout_s: float = 1.0
    heartbeat_timeout_s: float = 3.0
    pose_timeout_s: float = 0.5
    settle_s: float = 3.5  # after a fault ends or a daemon is up, the states /health gives are not judged this long
    tolerance_s: float = 0.6  # a state change may lag its cause by this much (detection, sampling)
    flowing_s: float = 2.0  # targets were flowing before a fault when at least `flowing_min` came in
    flowing_min: int = 4  # the `flowing_s` before it (a daemon meeting its time budget: ≥ 2 Hz of targets)
    warmup_s: float = 30.0  # resources are judged from this long after a daemon started
    resource_window_s: float = 30.0
    rss_growth: float = 0.05
    stopping_s: float = 3.0  # the samples of a daemon's last seconds (shutting down) are not judged
    max_set_gap_s: float = 1.0  # frame sets (target or not) must keep coming this often through a full disk
    skew_tolerance_s: float = (
        10.0  # whole seconds, renewed each second by a loop that lags under load; a jump is 3600 s
    )


@dataclass
class Recording:
    """Everything one soak recorded (module docstring)."""

    sent: list[Sent] = field(default_factory=list)
    captures: list[float] = field(default_factory=list)
    spans: list[Span] = field(default_factory=list)
    faults: list[Fault] = field(default_factory=list)
    stats: list[Stat] = field(default_factory=list)
    states: list[State] = field(default_factory=list)
    log_lines: list[str] = field(default_factory=list)
    daemon_log: list[tuple[float, str]] = field(default_factory=list)
    blind: list[tuple[float, float]] = field(default_factory=list)
    clock: list[tuple[float, float]] = field(default_factory=list)
    wall_skews: list[tuple[float, float]] = field(default_factory=list)
    horizon: float = math.inf  # what is known so far: a recovery due after it is not judged yet


def _span_at(spans: Sequence[Span], at: float) -> Span | None:
    """The process running at `at` (`spans` in start order, one at a time), or None."""
    index = bisect.bisect_right([span.started for span in spans], at) - 1
    return spans[index] if index >= 0 and spans[index].holds(at) else None


def _near(faults: Sequence[Fault], at: float, before_s: float) -> Sequence[Fault]:
    """The faults (in start order, one at a time) that may matter at `at`: begun by `at` + `before_s`, the
    last few (a fault ends before the next begins)."""
    index = bisect.bisect_right([fault.start for fault in faults], at + before_s)
    return faults[max(0, index - 3) : index]


def stale_targets(rec: Recording, limits: Limits) -> list[Breach]:
    """Targets with no result of the running daemon captured within `max_result_age_s` (+ slack) before them."""
    captures = sorted(rec.captures)
    breaches = []
    for sent in rec.sent:
        if sent.kind != "target" or any(a <= sent.at <= b for a, b in rec.blind):
            continue
        span = _span_at(rec.spans, sent.at)
        newest = bisect.bisect_right(captures, sent.at) - 1
        captured = captures[newest] if newest >= 0 else None
        if span is None:
            breaches.append(Breach("target_without_daemon", sent.at, "a target arrived while no daemon ran"))
        elif captured is None or captured < span.started:
            breaches.append(
                Breach("target_from_before_restart", sent.at, f"no result of the daemon started at {span.started:.3f}")
            )
        elif sent.at - captured > limits.max_result_age_s + limits.slack_s:
            breaches.append(
                Breach("stale_target", sent.at, f"newest capture {sent.at - captured:.3f} s old at arrival")
            )
    return breaches


def targets_while_lost(rec: Recording) -> list[Breach]:
    """Targets between a HEARTBEAT CRITICAL (camera lost) and the next ACTIVE one of the same daemon."""
    breaches, lost, span = [], False, None
    for sent in rec.sent:
        current = _span_at(rec.spans, sent.at)
        if current is not span:
            span, lost = current, False
        if sent.kind in ("lost", "ok"):
            lost = sent.kind == "lost"
        elif sent.kind == "target" and lost:
            breaches.append(Breach("target_while_camera_lost", sent.at, "target after HEARTBEAT CRITICAL"))
    return breaches


def recoveries(rec: Recording, limits: Limits) -> tuple[dict[str, list[float]], list[Breach]]:
    """Per fault kind, seconds from each fault's end to the next target, for the faults before which targets
    were flowing (`_flowing`); a breach when longer than 2 s (3 s after a restart)."""
    targets = [s.at for s in rec.sent if s.kind == "target"]
    faults = sorted(rec.faults, key=lambda f: f.start)
    times: dict[str, list[float]] = defaultdict(list)
    breaches = []
    for number, fault in enumerate(faults):
        if not _flowing(targets, fault.start, limits):
            continue  # targets were not going out before (e.g. results late on a busy CPU): nothing to recover
        limit = limits.restart_recovery_s if fault.kind in RESTARTS else limits.recovery_s
        if fault.end + limit > rec.horizon:
            continue
        after = bisect.bisect_left(targets, fault.end)
        following = faults[number + 1].start if number + 1 < len(faults) else float("inf")
        first = targets[after] if after < len(targets) else None
        if first is not None and first < following:
            times[fault.kind].append(first - fault.end)
        if (first is None or first - fault.end > limit) and fault.end + limit < following:
            took = "none" if first is None else f"{first - fault.end:.2f} s"
            breaches.append(
                Breach("slow_recovery", fault.end, f"{fault.kind}: first target after {took} (≤ {limit} s)")
            )
    return dict(times), breaches


def _flowing(targets: list[float], at: float, limits: Limits) -> bool:
    """Whether targets (sorted arrival times) were coming steadily just before `at`."""
    return bisect.bisect_left(targets, at) - bisect.bisect_left(targets, at - limits.flowing_s) >= limits.flowing_min


def _windows(stats: list[Stat], limits: Limits) -> tuple[list[Stat], list[Stat]] | None:
    """The first and the last `resource_window_s` after the warm-up of one process's samples."""
    started = stats[0].at
    judged = [s for s in stats if s.at >= started + limits.warmup_s]
    if not judged or judged[-1].at - judged[0].at < 2 * limits.resource_window_s:
        return None
    first = [s for s in judged if s.at <= judged[0].at + limits.resource_window_s]
    last = [s for s in judged if s.at >= judged[-1].at - limits.resource_window_s]
    return first, last


def resources(rec: Recording, limits: Limits) -> tuple[dict[int, dict[str, list[int]]], list[Breach]]:
    """Per process lived long enough: RSS (median of the last window ≤ first × (1 + rss_growth)), and the
    floor (minimum) of open descriptors and of threads in the last window not above their median in the
    first: a leak raises the floor, a connection or worker in flight does not, and a camera outage (no
    capture thread for a while) early on does not lower the baseline."""
    ends = {span.pid: span.ended for span in rec.spans if span.ended is not None}
    by_pid: dict[int, list[Stat]] = defaultdict(list)
    for stat in sorted(rec.stats, key=lambda s: s.at):
        if stat.at <= ends.get(stat.pid, math.inf) - limits.stopping_s:  # not while it shuts down
            by_pid[stat.pid].append(stat)
    summary, breaches = {}, []
    for pid, stats in by_pid.items():
        windows = _windows(stats, limits)
        if windows is None:
            continue
        first, last = windows
        rss = (statistics.median(s.rss_kb for s in first), statistics.median(s.rss_kb for s in last))
        fds = (int(statistics.median(s.fds for s in first)), min(s.fds for s in last))
        threads = (int(statistics.median(s.threads for s in first)), min(s.threads for s in last))
        summary[pid] = {"rss_kb": [int(v) for v in rss], "fds": list(fds), "threads": list(threads)}
        at = last[-1].at
        if rss[1] > rss[0] * (1 + limits.rss_growth):
            breaches.append(Breach("rss_growth", at, f"pid {pid}: RSS {rss[0]:.0f} → {rss[1]:.0f} kB"))
        if fds[1] > fds[0]:
            breaches.append(Breach("fd_leak", at, f"pid {pid}: open descriptors {fds[0]} → {fds[1]} at least"))
        if threads[1] > threads[0]:
            breaches.append(Breach("thread_leak", at, f"pid {pid}: threads {threads[0]} → {threads[1]} at least"))
    return summary, breaches


def _parsed(line: str) -> dict | None:
    try:
        record = json.loads(line)
    except ValueError:
        return None
    return record if isinstance(record, dict) else None


def log_lines(rec: Recording) -> list[Breach]:
    """Every results-log line parses, but for a line torn by a kill that the next run header owns up to
    (`previous_line_torn`); a header that claims a torn line must follow one."""
    breaches = []
    records = [_parsed(line) for line in rec.log_lines]
    for number, (line, record) in enumerate(zip(rec.log_lines, records, strict=True), start=1):
        following = records[number] if number < len(records) else None
        if record is None and not (following or {}).get("previous_line_torn"):
            breaches.append(Breach("torn_line", 0.0, f"results-log line {number} does not parse: {line[:60]!r}"))
        if record is not None and record.get("previous_line_torn") and (number < 2 or records[number - 2] is not None):
            breaches.append(Breach("false_torn_claim", 0.0, f"run header at line {number} claims a torn line"))
    return breaches


def disk_full(rec: Recording, limits: Limits) -> list[Breach]:
    """Per full-disk fault: its error logged at most once (none outside the faults), and the MAVLink output
    going on: frame sets (target or not) with no gap over `max_set_gap_s`. Whether targets come back after
    it is the recovery check's; during it they follow the CPU (filling 64 MB costs some), not the disk."""
    faults = [f for f in rec.faults if f.kind == "disk.full"]
    errors = [at for at, line in rec.daemon_log if DISK_FULL_MESSAGE in line and "results log" in line]
    sets = [s.at for s in rec.sent if s.kind in ("target", "no_target")]
    breaches = [
        Breach("disk_error_outside_fault", at, "results-log write error with a free disk")
        for at in errors
        if not any(f.start <= at <= f.end + limits.settle_s for f in faults)
    ]
    for fault in faults:
        if sum(fault.start <= at <= fault.end + limits.settle_s for at in errors) > 1:
            breaches.append(Breach("disk_full_logged_twice", fault.start, "the full disk was logged more than once"))
        points = [fault.start, *(at for at in sets if fault.start <= at <= fault.end), fault.end]
        gap, at = max((b - a, a) for a, b in zip(points, points[1:]))
        if gap > limits.max_set_gap_s:
            breaches.append(Breach("output_stopped_by_full_disk", at, f"no MAVLink frame set for {gap:.2f} s"))
    return breaches


def _expected(fault: Fault, state: State, limits: Limits) -> dict[str, object]:
    """What a fault in force makes `state`'s fields be (only the ones it settles)."""
    since = state.at - fault.start
    if state.at > fault.end:
        return {}
    if fault.kind in ("camera.stall", "camera.disconnect") and since >= limits.stall_timeout_s + limits.tolerance_s:
        return {"camera_lost": True}
    if (
        fault.kind in ("mavlink.silence", "mavlink.wrong_key")
        and since >= limits.heartbeat_timeout_s + limits.tolerance_s
    ):
        return {"link_connected": False, "mode": "camera"}
    return {}


def _disturbs(fault: Fault, field_name: str) -> bool:
    """Whether `fault` may change `field_name` from its calm value (so calm is not judged near it)."""
    group = fault.kind.partition(".")[0]
    if field_name == "camera_lost":
        return group in ("camera", "process")
    return group in ("mavlink", "process")


def _up_at(rec: Recording, span: Span) -> float:
    """When daemon `span` was up: its first HEARTBEAT (sent once its camera, pipeline and link are made, after
    the interpreter's start and the imports — 3 s on a busy 2-core machine), the instant a restart's fault
    ends; its process start when it never sent one (a daemon mute on MAVLink is judged from its start)."""
    beats = (s.at for s in rec.sent if s.kind in ("ok", "lost") and span.holds(s.at))
    return min(beats, default=span.started)


def states(rec: Recording, limits: Limits) -> list[Breach]:
    """/health and /metrics against the schedule: lost camera, link down and camera mode inside the faults
    that must cause them (`…_untrue` when not said: a status that hides a fault); camera up, link up and
    world mode when no fault that could change them is near (`…_not_back` when not: a status, or the
    daemon, slow to come back — on a loaded machine the world mode waits for results). A daemon's states
    are judged from `settle_s` after it was up (`_up_at`), the first one's as a restarted one's: its world
    mode needs `tracking.target_min_observations` fused results, which cannot begin before it is up."""
    calm = {"camera_lost": False, "link_connected": True, "mode": "world"}
    faults = sorted(rec.faults, key=lambda f: f.start)
    up = {span: _up_at(rec, span) for span in rec.spans}
    breaches = []
    for state in rec.states:
        span = _span_at(rec.spans, state.at)
        if span is None or state.at - up[span] < limits.settle_s:
            continue
        expected: dict[str, object] = {}
        near_faults = _near(faults, state.at, limits.tolerance_s)
        for fault in near_faults:
            expected.update(_expected(fault, state, limits))
        faulted = set(expected)
        for name, value in calm.items():
            near = any(
                _disturbs(f, name) and f.start - limits.tolerance_s <= state.at <= f.end + limits.settle_s
                for f in near_faults
            )
            if name not in expected and not near:
                expected[name] = value
        for name, value in expected.items():
            if getattr(state, name) != value:
                # a fault's state not said is a lie; the calm state not yet back is a slow recovery
                lie = name in faulted
                breaches.append(
                    Breach(
                        f"{state.endpoint}_{'untrue' if lie else 'not_back'}",
                        state.at,
                        f"{name} = {getattr(state, name)!r}, expected {value!r}",
                    )
                )
    return breaches


def log_order(rec: Recording) -> list[Breach]:
    """Within one camera opening of one run, each logged result was captured after the one before (the
    results log is ordered by the monotonic capture time, not by the wall clock)."""
    breaches, previous = [], -math.inf
    for number, line in enumerate(rec.log_lines, start=1):
        record = _parsed(line)
        if record is None:
            continue
        if "t" not in record:  # a run header or a camera-reopened marker: a new opening
            previous = -math.inf
            continue
        if record["t"] <= previous:
            breaches.append(
                Breach("log_out_of_order", record["t"], f"results-log line {number} captured before the line above")
            )
        previous = record["t"]
    return breaches


def wall_clock(rec: Recording, limits: Limits) -> list[Breach]:
    """The injected wall-clock jumps reached the daemon: each `Date` it sent at least `skew_tolerance_s`
    away from a jump shows the offset then in force (within that tolerance). Without this the soak
    could report a clock fault it never made. A breach is two readings in a row off the offset: a jump that
    did not reach the daemon shows in every reading after it, while a lone reading without the offset among
    ones with it is the shim's (libfaketime re-reads its offset file at every wall-clock read; once in a few
    thousand `Date`s one came back without it — seen twice, an hour apart), not a clock that moved back."""
    breaches = []
    jumps = sorted(rec.clock)
    times = [when for when, _ in jumps]
    run: list[tuple[float, float, float]] = []  # the current run of readings off the offset: (at, skew, offset)
    for at, skew in sorted(rec.wall_skews):
        if any(abs(at - when) < limits.skew_tolerance_s for when in times):
            continue
        index = bisect.bisect_right(times, at) - 1
        offset = jumps[index][1] if index >= 0 else 0.0
        if abs(skew - offset) <= limits.skew_tolerance_s:
            run = []
            continue
        run.append((at, skew, offset))
        if len(run) == 2:  # the second in a row: one breach for the run, at its first reading
            first_at, first_skew, first_offset = run[0]
            breaches.append(
                Breach(
                    "clock_jump_not_in_force",
                    first_at,
                    f"the daemon's Date is {first_skew:+.0f} s off, expected {first_offset:+.0f} s",
                )
            )
    return breaches


#: The invariants a soak on a busy machine can hold whatever its speed (`soak.py --gate safety`, the CI's):
#: nothing stale, nothing while the camera is lost, nothing from before a restart; every log line whole and
#: in order; a status that never hides a fault; descriptors and threads flat; the clock jumps in force.
#: The others (recovery times, the calm state back, RSS over a short run, the output's pace through a full
#: disk) depend on the CPU left to the daemon: reported, and gated by the full soak.
SAFETY = frozenset(
    {
        "stale_target",
        "target_without_daemon",
        "target_from_before_restart",
        "target_while_camera_lost",
        "torn_line",
        "false_torn_claim",
        "log_out_of_order",
        "health_untrue",
        "metrics_untrue",
        "fd_leak",
        "thread_leak",
        "disk_full_logged_twice",
        "disk_error_outside_fault",
        "clock_jump_not_in_force",
    }
)


def check(rec: Recording, limits: Limits) -> list[Breach]:
    """Every invariant over `rec`; the breaches, earliest first."""
    breaches = [
        *stale_targets(rec, limits),
        *targets_while_lost(rec),
        *recoveries(rec, limits)[1],
        *resources(rec, limits)[1],
        *log_lines(rec),
        *disk_full(rec, limits),
        *states(rec, limits),
        *log_order(rec),
        *wall_clock(rec, limits),
    ]
    return sorted(breaches, key=lambda b: b.at)
