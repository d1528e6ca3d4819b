"""Offline replay: a recording → the daemon's per-frame results (JSONL), a summary, and an overlay video.

After a flight, `replay_recording` runs every frame of a recording (a `branchrange record`
directory or a side-by-side video) through the pipeline the daemon builds from the same
configuration (`branchrange.core.frame_results`), as fast as the machine allows and without dropping
frames, so its results are the daemon's, frame for frame (timing aside). At `pace="recorded"` it
keeps the recording's schedule instead, as a camera would: the frames it has no time for are
dropped and counted (`dropped_late`). A corrupt frame is
skipped and a frame the pipeline rejects is logged, as the daemon does. The summary counts
frames, branches and tracks, and gives distance statistics and per-stage timing.
"""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from branchrange.config.loader import Config, pipeline_for
from branchrange.core.frame_result import FrameResult
from branchrange.core.frame_results import process_frame, result_line, run_header_line
from branchrange.core.overlay import draw_overlay
from branchrange.offline.overlay_video import OverlayVideoWriter, check_video
from camera.sources import CorruptFrameError, ReplaySource, open_source
from camera.sources.clock_sync import ClockSync
from camera.sources.rosbag import RosbagSource
from stereo.progress import progress_bar

log = logging.getLogger("branchrange.replay")
#: Called once per processed frame with its result and the pipeline's `FrameArtifacts` (the daemon's
#: observer contract; branchrange.onboard.foxglove_sink.FoxgloveSink is one).
Observer = Callable[[FrameResult, Any], None]


def _stats(values: list[float], digits: int) -> dict[str, float | int]:
    """count, min, median, mean, max and (population) std of `values`, rounded; just the count when empty."""
    if not values:
        return {"count": 0}
    return {
        "count": len(values),
        "min": round(min(values), digits),
        "median": round(statistics.median(values), digits),
        "mean": round(statistics.fmean(values), digits),
        "max": round(max(values), digits),
        "std": round(statistics.pstdev(values), digits),
    }


@dataclass
class ReplaySummary:
    """What a replay saw: frames, branches and tracks, distances (m), per-stage timing (ms).

    `add` takes each frame's result; `corrupt`/`rejected` count the frames that gave none, and
    `lost_at_end` the frames a killed or powered-off recording lists but cannot give. `tracks` are
    distinct branch ids over the sequence (stable ids when tracking is on).
    """

    recording: str
    frames: int = 0
    corrupt: int = 0
    rejected: int = 0
    frames_with_branches: int = 0
    frames_with_target: int = 0
    detections: int = 0
    wall_s: float = 0.0
    video: str | None = None
    video_codec: str | None = None
    unpaired: dict[str, int] | None = None
    lost_at_end: int = 0
    dropped_late: int = 0
    _tracks: set[int] = field(default_factory=set, init=False, repr=False)
    _target_tracks: set[int] = field(default_factory=set, init=False, repr=False)
    _distances: list[float] = field(default_factory=list, init=False, repr=False)
    _target_distances: list[float] = field(default_factory=list, init=False, repr=False)
    _timing: dict[str, list[float]] = field(default_factory=dict, init=False, repr=False)

    def add(self, result: FrameResult) -> None:
        """Count one frame's result."""
        self.frames += 1
        branches = result.branches
        self.detections += len(branches)
        self.frames_with_branches += bool(branches)
        for branch in branches:
            self._tracks.add(branch.id)
            self._distances.append(branch.distance_m)
        target = result.target
        if target is not None:
            self._target_tracks.add(target.id)
            self._target_distances.append(target.distance_m)
        self.frames_with_target += target is not None
        for stage, ms in result.timing_ms.items():
            self._timing.setdefault(stage, []).append(float(ms))

    def to_dict(self) -> dict[str, Any]:
        """The summary as JSON-ready values (distances in metres, timing in milliseconds per frame)."""
        timing = {
            stage: {k: v for k, v in _stats(values, 3).items() if k != "std"} for stage, values in self._timing.items()
        }
        return {
            "recording": self.recording,
            "frames": {
                "processed": self.frames,
                "corrupt": self.corrupt,
                "rejected": self.rejected,
                "lost_at_end": self.lost_at_end,
                "dropped_late": self.dropped_late,
                "with_branches": self.frames_with_branches,
                "with_target": self.frames_with_target,
                **({} if self.unpaired is None else {"unpaired": self.unpaired}),
            },
            "branches": {
                "detections": self.detections,
                "tracks": len(self._tracks),
                "target_tracks": len(self._target_tracks),
                "per_frame": round(self.detections / self.frames, 3) if self.frames else 0.0,
            },
            "distance_m": {"all": _stats(self._distances, 4), "target": _stats(self._target_distances, 4)},
            "timing_ms": timing,
            "wall_s": round(self.wall_s, 3),
            "fps": round(self.frames / self.wall_s, 3) if self.wall_s > 0 else 0.0,
            "video": None if self.video is None else {"path": self.video, "codec": self.video_codec},
        }

    def text(self) -> str:
        """The summary for a person, a few lines."""
        d = self.to_dict()
        f, b, t = d["frames"], d["branches"], d["distance_m"]["target"]
        lines = [
            f"replay of {self.recording}: {f['processed']} frames processed, {f['corrupt']} corrupt, "
            f"{f['rejected']} rejected, {f['dropped_late']} dropped late; {d['fps']:.1f} frames/s"
            + (f"; {self.lost_at_end} lost at the end of the recording" if self.lost_at_end else ""),
            f"branches: {b['detections']} cut points ({b['per_frame']:.2f} per frame) in {b['tracks']} tracks; "
            f"a target in {f['with_target']} frames ({b['target_tracks']} tracks)",
        ]
        if t["count"]:
            lines.append(
                f"target distance: median {t['median']:.3f} m, min {t['min']:.3f} m, max {t['max']:.3f} m, "
                f"std {t['std']:.3f} m"
            )
        stages = ", ".join(f"{stage} {s['mean']:.1f}" for stage, s in d["timing_ms"].items() if s["count"])
        lines.append(f"mean timing per frame (ms): {stages}")
        if self.unpaired and any(self.unpaired.values()):
            lines.append(f"unpaired images skipped: {self.unpaired['left']} left, {self.unpaired['right']} right")
        if d["video"]:
            lines.append(f"overlay video: {d['video']['path']} ({d['video']['codec']})")
        return "\n".join(lines)


def source_spec(recording: str | Path) -> str:
    """The `open_source` spec of what `branchrange replay` is given: a `rosbag:…`/`replay:…` spec as it is, a
    ROS 2 bag (a directory with metadata.yaml or .mcap/.db3 files — an unfinished bag lacks the metadata —, a
    .mcap or .db3 file) as `rosbag:PATH`, else `replay:PATH`."""
    text = str(recording)
    if text.startswith(("rosbag:", "replay:")):
        return text
    path = Path(text)
    bag_files = path.is_dir() and any(p.suffix in (".mcap", ".db3") for p in path.iterdir())
    is_bag = (path / "metadata.yaml").is_file() or bag_files or path.suffix in (".mcap", ".db3")
    return f"{'rosbag' if is_bag else 'replay'}:{text}"


def _overlay_frame(pipeline: Any, result: FrameResult) -> np.ndarray:
    """The overlay (RGB `uint8 H×W×3`) of the frame the pipeline just processed into `result`: its
    rectified left view, the masks it used (recorded or segmented) and the cut points."""
    return draw_overlay(pipeline.last.left, result, pipeline.last.masks)


def _notify(observers: Sequence[Observer], result: FrameResult, artifacts: Any) -> None:
    """Give the frame to every observer; one that fails is logged and the replay goes on, as in the daemon."""
    for observer in observers:
        try:
            observer(result, artifacts)
        except Exception:  # an observer (a viewer, a sink) must never stop the replay
            log.exception("frame %d: observer %r failed", result.frame.index, observer)


def replay_recording(
    recording: str | Path,
    cfg: Config,
    out_jsonl: str | Path,
    *,
    video: str | Path | None = None,
    progress: bool = True,
    observers: Sequence[Observer] = (),
    fps: float | None = None,
    pace: str = "fast",
    ignore_masks: bool = False,
    clock_sync: ClockSync | None = None,
    max_late_ms: float | None = None,
) -> ReplaySummary:
    """Process every frame of `recording` (a recording directory, a folder of pairs, a side-by-side video,
    a ROS 2 bag or a `rosbag:` spec, see `source_spec`) with the pipeline `cfg` describes; write a run
    header and one JSON line per frame to `out_jsonl` and, when `video` is given, an overlay video at the
    recording's frame rate (checked to read back frame for frame). Each result also goes to `observers`
    with the pipeline's `FrameArtifacts` (e.g. a FoxgloveSink).

    `fps` sets a folder of pairs' frame rate (default 15) or overrides a video's. `pace` "fast" processes
    every frame; "recorded" keeps the recording's schedule and drops the frames that come too late
    (camera.sources.ReplaySource; `max_late_ms` how late a frame may still come, default half a period).
    `ignore_masks` leaves a recording's masks unread, so the configured
    segmenter finds the branches as for a live camera. `clock_sync` starts the replay at a given time
    and/or announces its start (camera.sources.clock_sync).
    `cfg.camera.calibration` overrides the recording's calibration, as in the daemon. Raises
    `camera.sources.SourceError` when the recording cannot be opened or has no calibration.
    """
    spec = source_spec(recording)
    source = open_source(
        spec,
        calibration=cfg.camera.calibration or None,
        pace=pace,
        fps=fps,
        ignore_masks=ignore_masks,
        clock_sync=clock_sync,
        max_late_ms=max_late_ms,
    )
    summary = ReplaySummary(str(recording))
    writer = None
    try:
        pipeline = pipeline_for(cfg, source.calibration)
        if video is not None:
            rate = source.recorded_fps if isinstance(source, RosbagSource) else source.fps
            writer = OverlayVideoWriter(video, rate)
        out = Path(out_jsonl)
        out.parent.mkdir(parents=True, exist_ok=True)
        total = source.frame_count if isinstance(source, ReplaySource) else None
        start = time.perf_counter()
        with (
            out.open("w", encoding="utf-8") as results,
            progress_bar(total=total, unit="frame", desc="replay", disable=not progress) as bar,
        ):
            results.write(run_header_line("replay", cfg, spec))
            while True:
                try:
                    frame = next(source)
                except StopIteration:
                    break
                except CorruptFrameError as exc:
                    summary.corrupt += 1
                    log.warning("corrupt frame skipped: %s", exc)
                    bar.update()
                    continue
                bar.update()
                try:
                    result = process_frame(pipeline, frame)
                except ValueError as exc:
                    summary.rejected += 1
                    log.warning("frame %d rejected by the pipeline: %s", frame.index, exc)
                    continue
                results.write(result_line(result))
                summary.add(result)
                if writer is not None:
                    writer.write(_overlay_frame(pipeline, result))
                _notify(observers, result, pipeline.last)
        summary.wall_s = time.perf_counter() - start
        summary.dropped_late = source.dropped_late
        if isinstance(source, RosbagSource):
            summary.unpaired = source.unpaired
        if isinstance(source, ReplaySource):
            summary.lost_at_end = source.frames_lost_at_end
    finally:
        source.close()
        if writer is not None:
            writer.close()
    if writer is not None and writer.codec is not None and writer.size is not None:
        check_video(writer.path, writer.codec, writer.frames, writer.size)
        summary.video, summary.video_codec = str(writer.path), writer.codec.fourcc
    return summary
