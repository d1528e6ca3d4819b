"""Prometheus text exposition (format 0.0.4) written by hand: counters and histograms, thread-safe.

Request metrics are labelled by the route's path template (not the raw URL) so that the number
of series stays bounded.
"""

from __future__ import annotations

import bisect
import threading
from collections import defaultdict

LATENCY_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
Labels = tuple[tuple[str, str], ...]


def label_text(labels: Labels) -> str:
    """`{a="1",b="2"}` with Prometheus escaping of backslash, quote and newline."""
    if not labels:
        return ""
    esc = [(k, v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")) for k, v in labels]
    return "{" + ",".join(f'{k}="{v}"' for k, v in esc) + "}"


class Histogram:
    """Cumulative-bucket histogram of seconds per label set."""

    def __init__(self, buckets: tuple[float, ...] = LATENCY_BUCKETS_S):
        self.buckets = buckets
        self.counts: dict[Labels, list[int]] = defaultdict(lambda: [0] * (len(buckets) + 1))
        self.sums: dict[Labels, float] = defaultdict(float)

    def observe(self, labels: Labels, value: float) -> None:
        """Count one observation of `value` seconds under `labels`."""
        self.counts[labels][bisect.bisect_left(self.buckets, value)] += 1
        self.sums[labels] += value

    def lines(self, name: str) -> list[str]:
        """The exposition lines (`_bucket`, `_sum`, `_count`) of histogram `name`, label sets sorted."""
        out = []
        for labels, counts in sorted(self.counts.items()):
            running = 0
            for bound, count in zip((*map(repr, self.buckets), "+Inf"), counts):
                running += count
                out.append(f"{name}_bucket{label_text((*labels, ('le', bound)))} {running}")
            out.append(f"{name}_sum{label_text(labels)} {self.sums[labels]:.6f}")
            out.append(f"{name}_count{label_text(labels)} {running}")
        return out


class Metrics:
    """The service's metrics: HTTP requests and latencies, processed frames, inference time, errors."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._requests: dict[Labels, int] = defaultdict(int)
        self._latency = Histogram()
        self._inference = Histogram()
        self._errors: dict[Labels, int] = defaultdict(int)
        self._frames = 0

    def observe_request(self, route: str, method: str, status: int, seconds: float) -> None:
        """Count one HTTP request and its latency."""
        with self._lock:
            self._requests[(("route", route), ("method", method), ("status", str(status)))] += 1
            self._latency.observe((("route", route),), seconds)

    def observe_frame(self, seconds: float, source: str) -> None:
        """Count one processed frame (`source`: 'api' or 'daemon') and its processing time."""
        with self._lock:
            self._frames += 1
            self._inference.observe((("source", source),), seconds)

    def count_error(self, kind: str) -> None:
        """Count one error of a kind (e.g. 'bad_image', 'busy', 'corrupt_frame', 'camera_lost')."""
        with self._lock:
            self._errors[(("kind", kind),)] += 1

    def render(self) -> str:
        """All metrics in the Prometheus text format."""
        with self._lock:
            lines = [
                "# HELP branchrange_http_requests_total HTTP requests by route, method and status.",
                "# TYPE branchrange_http_requests_total counter",
            ]
            lines += [f"branchrange_http_requests_total{label_text(k)} {v}" for k, v in sorted(self._requests.items())]
            lines += [
                "# HELP branchrange_http_request_duration_seconds HTTP request latency.",
                "# TYPE branchrange_http_request_duration_seconds histogram",
            ]
            lines += self._latency.lines("branchrange_http_request_duration_seconds")
            lines += [
                "# HELP branchrange_frames_total Stereo frames processed.",
                "# TYPE branchrange_frames_total counter",
                f"branchrange_frames_total {self._frames}",
            ]
            lines += [
                "# HELP branchrange_frame_duration_seconds Time to process one frame.",
                "# TYPE branchrange_frame_duration_seconds histogram",
            ]
            lines += self._inference.lines("branchrange_frame_duration_seconds")
            lines += ["# HELP branchrange_errors_total Errors by kind.", "# TYPE branchrange_errors_total counter"]
            lines += [f"branchrange_errors_total{label_text(k)} {v}" for k, v in sorted(self._errors.items())]
        return "\n".join(lines) + "\n"
