"""Recordings that survive a kill at any instant: real SIGKILLs at seeded random instants, and the exact
leftovers of a kill inside an image write or inside the timestamps line, built on purpose.

Why: a drone's recorder is powered off or killed mid-frame; the recording must replay up to its last
complete frame and say how many frames were lost at the end, while damage anywhere else stays an error.
`benchmarks/` is not a package: its scripts import their siblings with their own folder on the path, so the
tests put it there first.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import pytest
from synth_recording import write_tree_recording

from branchrange.cli import main as branchrange_main
from camera.sources import CorruptFrameError, Recorder, RecordingFormatError, ReplaySource
from camera.sources.atomic_file import temporary_name

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
import recording_kill  # noqa: E402

FRAMES = 5
LOST_MESSAGE = "frame(s) lost at the end of the recording (power cut or kill while recording?)"


def test_twenty_recordings_killed_at_random_instants_replay_to_their_last_complete_frame(tmp_path: Path) -> None:
    trials = recording_kill.kill_trials(tmp_path, kills=20, seed=39)
    failures = [t for t in trials if not t.passed]
    assert not failures, failures
    assert sum(t.replayed > 0 for t in trials) >= 15  # the kills landed while frames were being written
    assert all(t.lost_at_end == 0 for t in trials)  # a kill loses no listed frame: rows follow their files


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    """FRAMES numbered frames, recorded and closed (as a kill after the last one would leave them, plus a manifest)."""
    with Recorder(tmp_path / "rec") as recorder:
        for index in range(FRAMES):
            recorder.write(recording_kill.numbered_frame(index))
    return tmp_path / "rec"


def _tear_last_row(recording: Path) -> None:
    """What a kill inside a frame's timestamps line leaves: the row cut before its line end."""
    csv = recording / "timestamps.csv"
    text = csv.read_text(encoding="utf-8")
    csv.write_text(text[: len(text) - 12], encoding="utf-8")


def _replayed_indices(recording: Path) -> tuple[list[int], int]:
    with ReplaySource(recording, pace="fast") as source:
        frames = list(source)
        for frame in frames:
            assert np.array_equal(frame.left, recording_kill.numbered_frame(frame.index).left)
        return [f.index for f in frames], source.frames_lost_at_end


def test_a_kill_inside_an_image_write_leaves_a_stray_temporary_file_that_replay_ignores(recording: Path) -> None:
    # the next frame's left image half written under its temporary name, no row yet
    partial = temporary_name(recording / "left" / f"{FRAMES:06d}.png")
    partial.write_bytes((recording / "left" / "000000.png").read_bytes()[:500])
    assert _replayed_indices(recording) == (list(range(FRAMES)), 0)


def test_a_kill_inside_the_timestamps_line_loses_that_one_frame_and_says_so(
    recording: Path, caplog: pytest.LogCaptureFixture
) -> None:
    _tear_last_row(recording)
    with caplog.at_level(logging.WARNING, logger="camera.sources.replay"):
        assert _replayed_indices(recording) == (list(range(FRAMES - 1)), 1)
    assert f"1 {LOST_MESSAGE}" in caplog.text


@pytest.mark.parametrize("damage", ["missing", "empty", "half written"])
def test_rows_at_the_end_whose_images_a_power_cut_lost_are_dropped_and_counted(recording: Path, damage: str) -> None:
    for index in (FRAMES - 2, FRAMES - 1):  # the kernel had not written the last two frames' images yet
        image = recording / "right" / f"{index:06d}.png"
        if damage == "missing":
            image.unlink()
        else:
            image.write_bytes(b"" if damage == "empty" else image.read_bytes()[:300])
    with (recording / "timestamps.csv").open("a", encoding="utf-8") as csv:
        csv.write("5,11666")  # and the next frame's row was cut off: three lost in all
    assert _replayed_indices(recording) == (list(range(FRAMES - 2)), 3)


def test_damage_before_the_end_stays_an_error(recording: Path) -> None:
    (recording / "left" / "000001.png").unlink()  # an image lost in the middle: that frame is corrupt, the rest plays
    source = ReplaySource(recording, pace="fast")
    assert next(source).index == 0
    with pytest.raises(CorruptFrameError, match=r"left/000001\.png: image file is missing"):
        next(source)
    assert [f.index for f in source] == [2, 3, 4] and source.frames_lost_at_end == 0
    lines = (recording / "timestamps.csv").read_text().splitlines(keepends=True)
    lines[2] = lines[2][:10] + "\r\n"  # a row cut short in the middle is damage, not an interrupted write
    (recording / "timestamps.csv").write_text("".join(lines))
    with pytest.raises(RecordingFormatError, match=r"timestamps\.csv: line 3 reads \['1', '10333333'\]"):
        ReplaySource(recording)


def test_a_recording_whose_only_row_was_cut_off_is_refused_and_one_whose_images_are_all_gone_is_corrupt(
    tmp_path: Path,
) -> None:
    with Recorder(tmp_path / "one") as recorder:
        recorder.write(recording_kill.numbered_frame(0))
    _tear_last_row(tmp_path / "one")
    with pytest.raises(RecordingFormatError, match="has no complete frames .its only row was cut off mid-write."):
        ReplaySource(tmp_path / "one")
    with Recorder(tmp_path / "two") as recorder:
        for index in range(2):
            recorder.write(recording_kill.numbered_frame(index))
    for image in (tmp_path / "two" / "left").iterdir():
        image.unlink()
    source = ReplaySource(tmp_path / "two")  # damaged, not interrupted: each frame is corrupt, none is "lost"
    assert source.frames_lost_at_end == 0
    for _ in range(2):
        with pytest.raises(CorruptFrameError, match="image file is missing"):
            next(source)


def test_branchrange_replay_of_a_killed_recording_says_what_was_lost_and_exits_0(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    recording = write_tree_recording(tmp_path / "tree", 3, 500_000_000)
    _tear_last_row(recording)
    out = tmp_path / "r.jsonl"
    with caplog.at_level(logging.WARNING):
        assert branchrange_main(["replay", str(recording), "--out", str(out), "--summary"]) == 0
    assert f"1 {LOST_MESSAGE}" in caplog.text
    printed = capsys.readouterr().out
    assert "a run header and 2 result lines" in printed and "1 lost at the end of the recording" in printed
