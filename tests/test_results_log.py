"""The daemon's results log is rotated by size, in whole lines, each file starting with the run header
(issue 39: ~56 MB an hour, no rotation), and the daemon writes it so with `log.results_max_mb`."""

from __future__ import annotations

import json

import pytest
from api_scene import BASELINE_M, FOCAL_PX, bar_scene

from branchrange.config.loader import Config, pipeline_for
from branchrange.config.sections import CameraConfig, LogConfig
from branchrange.core.frame_results import is_run_header, read_results, read_runs
from branchrange.core.pipeline import StereoConfig
from branchrange.core.settings_check import ConfigError
from branchrange.onboard.daemon import Daemon
from branchrange.onboard.results_log import ResultsLog
from camera.calibration import from_rectified
from camera.sources import Recorder, ReplaySource, StereoFrame

HEADER = json.dumps({"schema": "branchrange/run-header/v1", "kind": "test"}) + "\n"


def _line(number: int) -> str:
    """A 100-byte JSON line numbered `number`."""
    text = json.dumps({"n": number, "pad": ""})
    return json.dumps({"n": number, "pad": "x" * (99 - len(text))}) + "\n"


def _files_oldest_first(path):
    rotated = sorted(path.parent.glob(path.name + ".*"), key=lambda p: -int(p.suffix[1:]))
    return [*rotated, path]


def test_the_log_rotates_between_whole_lines_keeps_n_files_and_starts_each_with_the_header(tmp_path):
    path = tmp_path / "logs" / "results.jsonl"
    log = ResultsLog(path, HEADER, max_bytes=len(HEADER) + 250, keep=2)  # the header and two lines a file
    for number in range(9):
        log.write(_line(number))
    log.close()
    files = _files_oldest_first(path)
    assert [f.name for f in files] == ["results.jsonl.2", "results.jsonl.1", "results.jsonl"]
    assert log.rotations == 4  # files of lines 0-1 and 2-3 were deleted as the oldest
    contents = [f.read_text(encoding="utf-8") for f in files]
    assert all(text.startswith(HEADER) and text.endswith("\n") for text in contents)
    numbers = [json.loads(line)["n"] for text in contents for line in text.splitlines()[1:]]
    assert numbers == [4, 5, 6, 7, 8]
    assert all(f.stat().st_size <= len(HEADER) + 250 for f in files)


def test_a_line_longer_than_the_limit_still_gets_written_and_zero_never_rotates(tmp_path):
    log = ResultsLog(tmp_path / "r.jsonl", HEADER, max_bytes=50, keep=1)
    for number in range(3):
        log.write(_line(number))
    log.close()
    assert [len((tmp_path / name).read_text().splitlines()) for name in ("r.jsonl.1", "r.jsonl")] == [2, 2]
    endless = ResultsLog(tmp_path / "e.jsonl", HEADER)
    for number in range(50):
        endless.write(_line(number))
    endless.close()
    assert endless.rotations == 0 and len((tmp_path / "e.jsonl").read_text().splitlines()) == 51


def test_rotation_settings_are_checked():
    with pytest.raises(ConfigError, match="results_keep"):
        LogConfig(results_keep=0)
    with pytest.raises(ConfigError, match="results_max_mb"):
        LogConfig(results_max_mb=-1)
    with pytest.raises(ValueError, match="keep 0"):
        ResultsLog("unused.jsonl", HEADER, keep=0)


def test_the_daemon_rotates_its_log_at_results_max_mb(tmp_path):
    scene = bar_scene()
    calibration = from_rectified(FOCAL_PX, 159.5, 127.5, BASELINE_M, (320, 256))
    recording = tmp_path / "rec"
    with Recorder(recording, calibration=calibration) as recorder:
        for i in range(6):
            recorder.write(StereoFrame(scene.left, scene.right, 1_000_000_000 + i * 250_000_000, i))
    results = tmp_path / "results.jsonl"
    cfg = Config(
        camera=CameraConfig(source=f"replay:{recording}"),
        stereo=StereoConfig(max_disp=64),
        log=LogConfig(results_jsonl=str(results), results_max_mb=1500 / 2**20, results_keep=20),  # a result a file
    )
    daemon = Daemon(
        cfg, open_source=lambda: ReplaySource(recording), pipeline=pipeline_for(cfg, calibration), results_path=results
    )
    processed = daemon.run()  # to the recording's end (a loaded machine may drop a frame: the newest wins)
    daemon.close()
    files = _files_oldest_first(results)
    assert processed >= 4 and len(files) >= 3
    headers = [read_runs(f)[0][0] for f in files]
    assert all(is_run_header(h) and h == headers[0] for h in headers)  # one run, its header at each file's top
    indices = [r.frame.index for f in files for r in read_results(f)]
    assert len(indices) == processed and indices == sorted(indices)  # every result once, in order


def test_a_full_disk_drops_lines_without_raising_and_is_logged_once(caplog):
    """/dev/full answers every write with ENOSPC, as a full filesystem does (issue 39 item 2)."""
    log = ResultsLog("/dev/full", HEADER)
    for number in range(20):
        log.write(_line(number))
    log.close()
    errors = [r for r in caplog.records if r.levelname == "ERROR" and "cannot write" in r.getMessage()]
    assert len(errors) == 1 and "No space left on device" in errors[0].getMessage()
    assert log.dropped_lines == 21  # the header and the twenty lines


def test_a_line_torn_by_a_kill_is_ended_and_the_next_run_header_says_so(tmp_path):
    path = tmp_path / "results.jsonl"
    path.write_text(HEADER + _line(0) + _line(1)[:40], encoding="utf-8")  # killed in the middle of line 1
    ResultsLog(path, HEADER).close()
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[:2] == [HEADER.strip(), _line(0).strip()] and lines[2] == _line(1)[:40]
    assert json.loads(lines[3]) == {**json.loads(HEADER), "previous_line_torn": True}
    ResultsLog(path, HEADER).close()  # a clean end before: no claim of a torn line
    assert path.read_text(encoding="utf-8").endswith(HEADER)


def test_a_log_whose_rotation_can_outgrow_its_filesystem_is_warned_at_start(tmp_path, monkeypatch, caplog):
    """The 60-minute soak's 64 MiB log disk filled with the daemon's own rotated log (100 MiB × 11 allowed):
    the start says so, with the sizes, before it happens."""
    import shutil

    from branchrange.onboard import results_log

    def disk(free_mib: float):
        return lambda _path: shutil._ntuple_diskusage(2**40, 0, int(free_mib * 2**20))  # type: ignore[attr-defined]

    path = tmp_path / "results.jsonl"
    monkeypatch.setattr(results_log.shutil, "disk_usage", disk(64))
    ResultsLog(path, HEADER, max_bytes=100 * 2**20, keep=10).close()
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "can grow to 1100 MiB" in warned[0] and "64 MiB left" in warned[0]
    caplog.clear()
    monkeypatch.setattr(results_log.shutil, "disk_usage", disk(2000))
    ResultsLog(path, HEADER, max_bytes=100 * 2**20, keep=10).close()
    ResultsLog(path, HEADER, max_bytes=0).close()  # never rotated: the size is the user's choice
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
