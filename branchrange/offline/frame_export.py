"""A recording or ROS 2 bag → the frames worth labelling, as a COCO data set pre-annotated with today's masks.

Two passes over the source, so that a long recording is never held in memory:

1. every `every`-th frame goes through the pipeline (whole-frame stereo, no tracking: each frame on its
   own), then the learned and the structure segmenters, giving its `FrameStats`: colour, nearness,
   the mean confidence of its cut points, the two segmenters' agreement and its cut points, whose
   flicker against the frames scored before and after it is counted once all are in (`frame_selection`);
2. `select_frames` picks `count` of them, and the source is read again to write those frames' rectified
   left views and masks — the recording's own masks when it has them, else the configured segmenter's
   (`[segmenter] model`) — with `coco_export.write_coco`.

A replay's results file (JSONL) names its source in its run header (`branchrange/run-header/v1`):
`frames_source` turns it into that recording's spec, so `export-frames results.jsonl` exports from the
recording the replay ran on (a daemon's log of a live camera names no file to read frames back from).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from branchrange.config.loader import Config, pipeline_for
from branchrange.core.frame_results import process_frame, read_runs
from branchrange.core.segmentation.choose import make_segmenter
from branchrange.offline.coco_export import LabelledFrame, write_coco
from branchrange.offline.frame_selection import (
    FrameStats,
    colour_histogram,
    mask_agreement,
    select_frames,
    with_flicker,
)
from branchrange.offline.replay import source_spec
from camera.sources import CorruptFrameError, SourceConfigError, SourceUnavailable, StereoFrame, open_source
from stereo.progress import progress_bar

log = logging.getLogger("branchrange.export_frames")
#: The segmenters whose disagreement marks a frame as uncertain: the learned one and the 3D-structure one.
REFERENCE_SEGMENTERS = ("learned", "structure")


@dataclass(frozen=True)
class ExportSummary:
    """What an export did: frames scored, unreadable and rejected by the pipeline, the frames picked, where
    the data set is."""

    source: str
    scored: int
    corrupt: int
    rejected: int
    picked: tuple[FrameStats, ...]
    annotations: Path


def frames_source(source: str | Path) -> str:
    """The `open_source` spec of what `export-frames` is given: as `source_spec` does for a recording or bag;
    for a replay's results file (`.jsonl`) the source its last run header names, which must be a file source.

    Raises `SourceConfigError` for a results file without a run header or whose run read a live camera."""
    text = str(source)
    if not text.endswith(".jsonl"):
        return source_spec(text)
    try:
        runs = read_runs(text)
    except (OSError, ValueError) as exc:  # missing, unreadable or not JSON lines
        raise SourceConfigError(f"{text}: not a readable results file ({exc})") from None
    headers = [header for header, _ in runs if header is not None]
    if not headers:
        raise SourceConfigError(f"{text}: no run header names the frames' source; give the recording itself")
    spec = str(headers[-1].get("source", ""))
    if not spec.startswith(("replay:", "rosbag:")):
        raise SourceConfigError(
            f"{text}: its run read {spec!r}, not a recording or bag frames can be read back from; "
            "export from the recording of that flight instead"
        )
    return spec


class FrameAnalyser:
    """The pipeline and the reference segmenters of an export, for the frames of one source."""

    def __init__(self, cfg: Config, calibration: Any) -> None:
        whole_frame = dataclasses.replace(
            cfg,
            stereo=dataclasses.replace(cfg.stereo, mode="full"),
            cutpoints=dataclasses.replace(cfg.cutpoints, tracking=False),
        )
        self.pipeline = pipeline_for(whole_frame, calibration)
        self.max_disparity = float(cfg.stereo.max_disp)
        self.references = {name: make_segmenter(name, learned=cfg.segmenter.learned) for name in REFERENCE_SEGMENTERS}

    def labelled(self, frame: StereoFrame) -> LabelledFrame:
        """The frame's rectified left view and masks (the recording's, else the configured segmenter's), with its
        disparity, stereo confidence and camera (what a fine-tune on the corrected labels reads)."""
        process_frame(self.pipeline, frame)
        last = self.pipeline.last
        geometry = self.pipeline.geometry_for(last.left.shape[1], last.left.shape[0])
        return LabelledFrame(
            last.left, last.masks, frame.index, frame.timestamp_ns, last.disparity, last.confidence, geometry
        )

    def stats(self, frame: StereoFrame) -> FrameStats:
        """The frame's selection statistics (`FrameStats`)."""
        result = process_frame(self.pipeline, frame)
        last = self.pipeline.last
        valid = np.isfinite(last.disparity) & (last.disparity > 0)
        near = float(last.disparity[valid].mean()) / self.max_disparity if valid.any() else 0.0
        confidences = [b.confidence for b in result.branches]
        geometry = self.pipeline.geometry_for(last.left.shape[1], last.left.shape[0])
        branch_pixels = []
        for segmenter in self.references.values():
            masks = last.masks
            if masks is None or masks.source != segmenter.name:
                masks = segmenter.segment(last.left, last.disparity, geometry, last.confidence)
            branch_pixels.append(np.isin(masks.labels, masks.branch_ids()))
        return FrameStats(
            index=frame.index,
            timestamp_ns=frame.timestamp_ns,
            colour=colour_histogram(last.left),
            near=min(1.0, near),
            confidence=float(np.mean(confidences)) if confidences else 0.0,
            agreement=mask_agreement(*branch_pixels),
            cut_points=np.array([b.cut_point_m for b in result.branches], dtype=float).reshape(-1, 3),
        )


def _readable(source: Any, every: int = 1) -> Iterator[StereoFrame | None]:
    """Every `every`-th frame of an open `source`, None for a corrupt one."""
    position = 0
    while True:
        try:
            frame = next(source)
        except StopIteration:
            return
        except CorruptFrameError:
            frame = None
        if position % every == 0:
            yield frame
        position += 1


def _picked_frames(spec: str, cfg: Config, analyser: FrameAnalyser, wanted: set[int]) -> Iterator[LabelledFrame]:
    """The frames of `spec` whose index is in `wanted`, labelled, the source read again from its start."""
    source = open_source(spec, calibration=cfg.camera.calibration or None, pace="fast")
    try:
        for frame in _readable(source):
            if frame is not None and frame.index in wanted:
                yield analyser.labelled(frame)
    finally:
        source.close()


def export_frames(
    source: str | Path,
    cfg: Config,
    out_dir: str | Path,
    *,
    count: int = 50,
    min_spacing_s: float = 2.0,
    every: int = 1,
    version: str = "",
    progress: bool = True,
) -> ExportSummary:
    """Pick up to `count` frames of `source` (a recording, a folder of pairs, a video, a ROS 2 bag, a
    `replay:`/`rosbag:` spec or a replay's results file), scoring every `every`-th one, at least
    `min_spacing_s` apart, and write them to `out_dir` as a COCO data set (`coco_export`).

    `cfg`: the stereo, mask and segmenter settings (`[stereo]`, `[masks]`, `[segmenter]`), and
    `camera.calibration` in place of the source's own. Raises `camera.sources.SourceError` for a source
    that cannot be opened or has no readable frame, `ValueError` for settings it cannot use, and
    `coco_export.CocoExportError` (an `OSError`) when the data set cannot be written.
    """
    if count < 1 or every < 1 or not min_spacing_s >= 0:
        raise ValueError(
            f"--count {count}, --every {every}, --min-spacing-s {min_spacing_s}: expected a count ≥ 1, "
            "every ≥ 1 and a spacing ≥ 0 s"
        )
    spec = frames_source(source)
    scored: list[FrameStats] = []
    corrupt, rejected = 0, []
    opened = open_source(spec, calibration=cfg.camera.calibration or None, pace="fast")
    try:
        analyser = FrameAnalyser(cfg, opened.calibration)
        with progress_bar(unit="frame", desc="scoring", disable=not progress) as bar:
            for frame in _readable(opened, every):
                bar.update()
                if frame is None:
                    corrupt += 1
                    continue
                try:
                    scored.append(analyser.stats(frame))
                except ValueError as exc:  # the pipeline's input errors: a pair it refuses, a size off its calibration
                    rejected.append(f"frame {frame.index}: {exc}")
                    log.warning("frame %d skipped: %s", frame.index, exc)
    finally:
        opened.close()
    if not scored:
        why = f"; {rejected[0]}" if rejected else ""
        raise SourceUnavailable(
            f"{spec}: no frame could be scored ({corrupt} unreadable, {len(rejected)} rejected{why}); "
            "expected a readable recording"
        )
    picked = select_frames(with_flicker(scored), count, int(round(min_spacing_s * 1e9)))
    annotations = write_coco(out_dir, _picked_frames(spec, cfg, analyser, {s.index for s in picked}), spec, version)
    return ExportSummary(spec, len(scored), corrupt, len(rejected), tuple(picked), annotations)
