"""`record` from a plain folder of pairs, `record`/`replay` exit codes on deleted and truncated
recordings, the run header of results logs, and progress output when stderr is not a terminal."""

from __future__ import annotations

import dataclasses
import io
import json
import shutil

import numpy as np
import pytest
from synth_recording import still_camera_frames, tree_scene, write_tree_recording

from branchrange.cli import main as branchrange_main
from branchrange.config.loader import Config
from branchrange.core.frame_results import RUN_HEADER_SCHEMA, config_sha256, read_results, read_runs, run_header_line
from branchrange.core.pipeline import StereoConfig
from camera.sources import ReplaySource
from camera.sources.image_files import write_mask, write_rgb
from stereo.progress import progress_bar

PERIOD_NS = 500_000_000
FRAMES = 3


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_tree_recording(tmp_path_factory.mktemp("rec") / "tree", FRAMES, PERIOD_NS)


@pytest.fixture(scope="module")
def pair_folder(tmp_path_factory):
    """left/ right/ mask/ named so that plain string order would be wrong (frame_2 before frame_10)."""
    folder = tmp_path_factory.mktemp("pairs")
    frames = still_camera_frames(tree_scene(), FRAMES, PERIOD_NS, with_masks=True)
    for sub in ("left", "right", "mask"):
        (folder / sub).mkdir()
    for frame, number in zip(frames, (2, 10, 11)):
        write_rgb(folder / "left" / f"frame_{number}.png", frame.left)
        write_rgb(folder / "right" / f"frame_{number}.png", frame.right)
        write_mask(folder / "mask" / f"frame_{number}.png", frame.mask)
    return folder, frames


def test_record_from_a_folder_of_pairs_pairs_by_name_and_stamps_by_fps(pair_folder, recording, tmp_path, capsys):
    folder, frames = pair_folder
    out = tmp_path / "out"
    status = branchrange_main(
        [
            "record",
            "--source",
            f"replay:{folder}",
            "--out",
            str(out),
            "--fps",
            "10",
            "--calibration",
            str(recording / "calibration.yaml"),
        ]
    )
    assert status == 0, capsys.readouterr().err
    replayed = list(ReplaySource(out, pace="fast"))
    assert [f.timestamp_ns for f in replayed] == [0, 100_000_000, 200_000_000]
    for original, back in zip(frames, replayed):
        assert np.array_equal(back.left, original.left) and np.array_equal(back.right, original.right)
        assert np.array_equal(back.mask, original.mask)
    assert replayed[0].left.shape[:2] == frames[0].left.shape[:2]
    default = list(ReplaySource(folder, pace="fast"))
    assert default[1].timestamp_ns == round(1e9 / 15)  # 15 fps unless told


def test_a_folder_of_pairs_with_unequal_sides_or_masks_is_refused(pair_folder, tmp_path, capsys):
    folder, _ = pair_folder
    uneven = tmp_path / "uneven"
    shutil.copytree(folder, uneven)
    (uneven / "right" / "frame_11.png").unlink()
    assert branchrange_main(["record", "--source", f"replay:{uneven}", "--out", str(tmp_path / "o")]) == 2
    assert "left/ holds 3 images and right/ 2" in capsys.readouterr().err
    (uneven / "left" / "frame_11.png").unlink()
    assert branchrange_main(["record", "--source", f"replay:{uneven}", "--out", str(tmp_path / "o2")]) == 2
    assert "mask/ holds 3 images for 2 pairs" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert branchrange_main(["record", "--source", f"replay:{tmp_path / 'empty'}", "--out", str(tmp_path / "o3")]) == 2
    assert "neither a recording" in capsys.readouterr().err


def _damage(recording, tmp_path, how):
    broken = tmp_path / how
    shutil.copytree(recording, broken)
    if how == "deleted":
        shutil.rmtree(broken)
    elif how == "row cut short in the middle of the csv":  # a cut-off last row is an interrupted write (replays)
        lines = (broken / "timestamps.csv").read_text().splitlines(keepends=True)
        lines[1] = lines[1][:20] + "\n"
        (broken / "timestamps.csv").write_text("".join(lines))
    elif how == "truncated manifest":
        text = (broken / "recording.json").read_text()
        (broken / "recording.json").write_text(text[: len(text) // 2])
    else:  # images gone
        shutil.rmtree(broken / "left")
    return broken


@pytest.mark.parametrize(
    "how", ["deleted", "row cut short in the middle of the csv", "truncated manifest", "images gone"]
)
def test_record_and_replay_agree_on_exit_code_2_for_a_deleted_or_truncated_recording(recording, tmp_path, capsys, how):
    broken = _damage(recording, tmp_path, how)
    assert branchrange_main(["record", "--source", f"replay:{broken}", "--out", str(tmp_path / "rec")]) == 2
    record_err = capsys.readouterr().err
    assert branchrange_main(["replay", str(broken), "--out", str(tmp_path / "r.jsonl")]) == 2
    replay_err = capsys.readouterr().err
    for err, command in ((record_err, "record"), (replay_err, "replay")):
        assert f"branchrange {command}: " in err and "Traceback" not in err
        assert str(broken) in err


def test_the_help_texts_state_the_exit_codes(capsys):
    for command in ("record", "replay", "export-frames"):
        with pytest.raises(SystemExit):
            branchrange_main([command, "--help"])
        text = capsys.readouterr().out
        assert "exit codes (the same for record, replay and export-frames):" in text and "2  bad input" in text


def test_replay_writes_a_run_header_and_readers_skip_it(recording, tmp_path):
    out = tmp_path / "r.jsonl"
    assert branchrange_main(["replay", str(recording), "--out", str(out)]) == 0
    first = json.loads(out.read_text().splitlines()[0])
    assert first["schema"] == RUN_HEADER_SCHEMA and first["kind"] == "replay"
    assert first["source"] == f"replay:{recording}" and first["started_utc"].endswith("Z")
    defaults = Config()  # replay runs the defaults with camera.source set to the recording
    expected = dataclasses.replace(defaults, camera=dataclasses.replace(defaults.camera, source=f"replay:{recording}"))
    assert first["config_sha256"] == config_sha256(expected) and first["version"][0].isdigit()
    results = [r.to_json_dict() for r in read_results(out)]
    assert len(results) == FRAMES and all(r["schema"] == "branchrange/v1" for r in results)
    # Two runs appended to one log (as the daemon's results_jsonl does) stay apart.
    other = Config(stereo=StereoConfig(max_disp=64))
    with out.open("a", encoding="utf-8") as log:
        log.write(run_header_line("daemon", other, "zed:0"))
        log.write(json.dumps(results[0]) + "\n")
    runs = read_runs(out)
    assert [(h["kind"], len(r)) for h, r in runs] == [("replay", FRAMES), ("daemon", 1)]
    assert runs[0][0]["config_sha256"] != runs[1][0]["config_sha256"]


def test_progress_off_a_terminal_prints_sparse_plain_lines(monkeypatch):
    """1000 updates 0.5 s apart (a fake clock): one line per 30 s, no carriage returns."""
    import tqdm.std

    clock = [1000.0]
    monkeypatch.setattr(tqdm.std, "time", lambda: clock[0])
    stream = io.StringIO()
    with progress_bar(total=1000, desc="replay", unit="frame", file=stream) as bar:
        for _ in range(1000):
            clock[0] += 0.5
            bar.update(1)
    text = stream.getvalue()
    lines = text.splitlines()
    assert "\r" not in text and text.endswith("\n")
    assert 10 <= len(lines) <= 25  # 500 s of updates: ~17 lines, not 1000
    assert lines[-1].startswith("replay: 100%") and "1000/1000" in lines[-1]
