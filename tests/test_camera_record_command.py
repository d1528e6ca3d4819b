"""`branchrange record`: a replay recorded again through the command gives back the same pairs."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from branchrange.cli import COMMAND_MODULES
from camera import StereoCalibration
from camera.sources import Recorder, ReplaySource, StereoFrame, record
from stereo.cli import build_parser


def _run(argv: list[str]) -> int:
    """Run `branchrange ARGV` with only the record subcommand registered."""
    args = build_parser("branchrange", "test", ["branchrange.commands.record"]).parse_args(argv)
    return args.func(args)


@pytest.fixture
def source_recording(tmp_path: Path) -> Path:
    rng = np.random.default_rng(5)
    k = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    calibration = StereoCalibration(k, np.zeros(5), k, np.zeros(5), np.eye(3), np.array([-0.063, 0, 0]), (32, 24))
    frames = [
        StereoFrame(
            rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
            rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
            10_000 + 1000 * i,
            i,
        )
        for i in range(5)
    ]
    with Recorder(tmp_path / "original", calibration=calibration) as recorder:
        record(iter(frames), recorder)
    return tmp_path / "original"


def test_record_command_is_registered() -> None:
    assert "branchrange.commands.record" in COMMAND_MODULES


def test_record_command_copies_frames_and_calibration(
    source_recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "copy"
    assert _run(["record", "--source", f"replay:{source_recording}", "--out", str(out), "--frames", "3"]) == 0
    assert "recorded 3 pairs" in capsys.readouterr().out
    original = list(ReplaySource(source_recording, pace="fast"))[:3]
    copy = ReplaySource(out, pace="fast")
    copied = list(copy)
    assert len(copied) == 3
    for a, b in zip(original, copied):
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert a.timestamp_ns == b.timestamp_ns
    assert copy.calibration == ReplaySource(source_recording).calibration
    manifest = json.loads((out / "recording.json").read_text())
    assert manifest["source"] == f"replay:{source_recording}" and manifest["complete"] is True


def test_record_command_skips_corrupt_frames(
    source_recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (source_recording / "left" / "000001.png").write_bytes(b"garbage")
    out = tmp_path / "copy"
    assert _run(["record", "--source", f"replay:{source_recording}", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "recorded 4 pairs" in captured.out and "skipped 1 corrupt frames" in captured.out
    assert "left/000001.png" in captured.err
    assert [f.timestamp_ns for f in ReplaySource(out, pace="fast")] == [10_000, 12_000, 13_000, 14_000]


def test_record_command_rejects_bad_source_and_existing_output(
    source_recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _run(["record", "--source", "webcam:0", "--out", str(tmp_path / "x")]) == 2
    assert "expected zed" in capsys.readouterr().err
    assert _run(["record", "--source", f"replay:{tmp_path / 'missing'}", "--out", str(tmp_path / "y")]) == 2
    assert "no such recording" in capsys.readouterr().err
    assert _run(["record", "--source", f"replay:{source_recording}", "--out", str(source_recording)]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_record_command_stops_on_an_error_and_keeps_what_it_wrote(
    source_recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cv2.imwrite(str(source_recording / "left" / "000003.png"), np.zeros((12, 16, 3), np.uint8))
    out = tmp_path / "copy"
    assert _run(["record", "--source", f"replay:{source_recording}", "--out", str(out)]) == 1
    captured = capsys.readouterr()
    assert "recorded 3 pairs" in captured.out and "stopped by an error" in captured.out
    assert "frame 3 is 16×12; the recording is 32×24" in captured.err
    copy = ReplaySource(out, pace="fast")
    assert [f.index for f in copy] == [0, 1, 2]
    assert json.loads((out / "recording.json").read_text())["complete"] is True


def test_record_command_rejects_a_file_as_output(
    source_recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "a_file"
    target.write_text("not a directory")
    assert _run(["record", "--source", f"replay:{source_recording}", "--out", str(target), "--overwrite"]) == 2
    assert f"--out {target}" in capsys.readouterr().err
