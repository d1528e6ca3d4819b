"""What /health says, as Prometheus lines for /metrics: every count and state, derived from the same body.

Why derived rather than listed: /metrics once lacked the late / dropped / reopen counters and the
peer's mode and armed state that /health had. Walking /health's body means a key added there shows
up here too (tests/test_health_metrics.py compares the two endpoints). Each leaf becomes one series:
- a number or boolean (True = 1; None = NaN, "not known yet") at path `section.key[.sub]` →
  `branchrange_section_key_sub`; the ones that only grow are counters, named `…_total` (`COUNTERS`);
- the strings of a section (stereo mode, backend, link mode, source) → labels of one
  `branchrange_section_info` series of value 1 (free text such as `last_error` is left out:
  a label's value must come from a small set).
Some keep the names they had before this mirror existed (`KEPT_NAMES`), for the dashboards using them.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from api.metrics import label_text

PREFIX = "branchrange"
KeyPath = tuple[str, ...]  # a key of /health, section first: ("camera", "late")

#: /health leaves that only grow: Prometheus counters.
COUNTERS: frozenset[KeyPath] = frozenset(
    {
        ("camera", "frames"),
        ("camera", "dropped"),
        ("camera", "skipped"),
        ("camera", "corrupt"),
        ("camera", "reopens"),
        ("camera", "late"),
        ("camera", "repeated"),
        ("stereo_workers", "restarts"),
        ("stereo_workers", "lost_frames"),
        ("mavlink", "reconnects"),
        ("mavlink", "sent"),
        ("mavlink", "send_errors"),
        ("mavlink", "received"),
        ("mavlink", "signature_failures"),
        ("mavlink", "frames_sent"),
        ("mavlink", "no_target_frames"),
        ("mavlink", "setpoints_sent"),
        ("mavlink", "message_interval_acks"),
        ("mavlink", "unfused_results"),
        ("mavlink", "vehicle_state", "messages"),
    }
)
#: Series named before /metrics mirrored /health: path → name after the prefix.
KEPT_NAMES: dict[KeyPath, str] = {
    ("mavlink", "received"): "mavlink_messages_received_total",
    ("mavlink", "sent"): "mavlink_messages_sent_total",
    ("mavlink", "signature_failures"): "mavlink_signature_failures_total",
    ("mavlink", "peer_heartbeat_age_s"): "mavlink_heartbeat_age_seconds",
}
#: Free-text strings (or None): never labels, never series.
FREE_TEXT: frozenset[KeyPath] = frozenset({("mavlink", "last_error")})
#: Words that may be None (no estimator in the API): a label with an empty value then, not a NaN series.
WORDS_OR_NONE: frozenset[KeyPath] = frozenset({("model", "backend")})
#: HELP texts of the series whose name does not say enough; the others get "/health's `path`".
HELP: dict[KeyPath, str] = {
    ("camera", "lost"): "1 while the camera is lost (stalled, gone or unreadable); the relay sends no target.",
    ("model", "segmenter_ood_flagged"): "1 when the segmenter's model did not look like it knew the last frame "
    "(out of its training domain); NaN without the signal.",
    ("model", "segmenter_ood_score"): "Share of the model's training-domain reference frames that hesitated less "
    "than the last frame (0..1); NaN without the signal.",
    ("camera", "frames"): "Results published by the daemon.",
    ("camera", "dropped"): "Camera frames replaced by a newer one before the stereo stage took them, and frames a "
    "stereo worker took with it when it died.",
    ("stereo_workers", "count"): "Processes running the stereo stage (stereo.workers; 1: the daemon's own thread).",
    ("stereo_workers", "restarts"): "Stereo worker processes that died and were started again.",
    ("stereo_workers", "lost_frames"): "Frames a dying stereo worker took with it (counted in camera dropped too).",
    ("camera", "skipped"): "Stereo outputs replaced before the geometry stage took them.",
    ("camera", "corrupt"): "Camera frames that could not be decoded.",
    ("camera", "reopens"): "Times the watchdog closed the stalled camera and opened it again.",
    ("camera", "late"): "Results older than mavlink.max_result_age_s when published (sent as no target).",
    ("camera", "repeated"): "Frames skipped as captured no later than the frame before them (repeated, out of order).",
    ("mavlink", "connected"): "1 while the autopilot's HEARTBEAT arrives within the timeout.",
    ("mavlink", "peer_heartbeat_age_s"): "Seconds since the autopilot's newest HEARTBEAT (NaN: never).",
    ("mavlink", "peer", "armed"): "1 while the autopilot's HEARTBEAT says it is armed.",
    ("mavlink", "peer", "custom_mode"): "The autopilot's flight mode (HEARTBEAT custom_mode).",
    ("mavlink", "received"): "MAVLink messages received.",
    ("mavlink", "sent"): "MAVLink messages sent.",
    ("mavlink", "signature_failures"): "Messages dropped for a missing or wrong signature.",
    ("mavlink", "vehicle_state", "available"): "1 while the vehicle pose is known (targets in local NED).",
    ("mavlink", "tracks"): "Fresh fused target tracks.",
}


def metric_name(path: KeyPath) -> str:
    """The series name of the /health leaf at `path` (e.g. ("camera", "late") → branchrange_camera_late_total)."""
    kept = KEPT_NAMES.get(path)
    if kept is not None:
        return f"{PREFIX}_{kept}"
    return f"{PREFIX}_{'_'.join(path)}" + ("_total" if path in COUNTERS else "")


def health_leaves(body: dict[str, Any], path: KeyPath = ()) -> Iterator[tuple[KeyPath, Any]]:
    """Every (path, value) of /health's body whose value is not an object; absent sections give none."""
    for key, value in body.items():
        if isinstance(value, dict):
            yield from health_leaves(value, (*path, key))
        else:
            yield (*path, key), value


def _number(value: Any) -> str:
    """A Prometheus sample value: booleans as 1/0, None as NaN."""
    if value is None:
        return "NaN"
    return str(int(value)) if isinstance(value, bool) else repr(value)


def _peer_labels(body: dict[str, Any]) -> str:
    """The labels `branchrange_mavlink_connected` carries: the peer's system and component ids ("" before one)."""
    peer = (body.get("mavlink") or {}).get("peer") or {}
    return label_text(
        (("system_id", str(peer.get("system_id", ""))), ("component_id", str(peer.get("component_id", ""))))
    )


def health_metrics(body: dict[str, Any]) -> list[str]:
    """The Prometheus lines (HELP, TYPE, sample) of every count and state in /health's `body`."""
    lines: list[str] = []
    infos: dict[str, list[tuple[str, str]]] = {}
    for path, value in health_leaves(body):
        if path in FREE_TEXT:
            continue
        if isinstance(value, str) or path in WORDS_OR_NONE:
            section = path[0] if len(path) > 1 else "health"
            infos.setdefault(section, []).append(("_".join(path[1:]) or path[0], value or ""))
            continue
        if value is not None and not isinstance(value, (bool, int, float)):
            continue  # a list: not a count or a state
        name = metric_name(path)
        labels = _peer_labels(body) if path == ("mavlink", "connected") else ""
        lines += [
            f"# HELP {name} {HELP.get(path, '/health ' + '.'.join(path) + '.')}",
            f"# TYPE {name} {'counter' if path in COUNTERS else 'gauge'}",
            f"{name}{labels} {_number(value)}",
        ]
    for section, labels in infos.items():
        name = f"{PREFIX}_{section}_info"
        lines += [
            f"# HELP {name} The states /health gives as words, as labels (value always 1).",
            f"# TYPE {name} gauge",
            f"{name}{label_text(tuple(labels))} 1",
        ]
    return lines
