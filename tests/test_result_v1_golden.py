"""The `branchrange/v1` output, byte for byte: `demo`, `estimate` and `replay` against files written before
the typed `FrameResult` replaced the result dict (tests/data/result_v1/).

Only what differs from run to run is masked before comparing: the values of `timing_ms`, the run
header's time and version, and the seconds the demo prints. Key order, which optional keys appear, every
string and every integer are compared as written; a decimal number may differ from the golden one by two units
of its last written digit and no more: another CPU's floating-point rounding (an Intel machine wrote
−0.11142 where these files hold −0.11143), never another result. `BRANCHRANGE_WRITE_GOLDEN=1` rewrites the
files (only after a deliberate, documented change of the format).
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import cv2
from synth_recording import write_tree_recording

from branchrange.cli import main
from branchrange.core.frame_results import read_results, result_line
from stereo.io import write_rgb
from stereo.synth import SynthCamera, render_scene
from stereo.synth.writer import write_mask

GOLDEN = Path(__file__).with_name("data") / "result_v1"
WRITE = os.environ.get("BRANCHRANGE_WRITE_GOLDEN") == "1"
_TIMING = re.compile(r'("timing_ms": ?\{)([^{}]*)(\})')
_NUMBER = re.compile(r'(": ?)-?[0-9][0-9.e+-]*')
#: A number in written output: its sign, digits, decimals and exponent (not part of a name or a hex digest).
_WRITTEN_NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.(\d+))?(?:e[+-]?\d+)?(?![\w.])")


def _mask_varying(text: str) -> str:
    """`text` with every `timing_ms` value, the run header's start time and the version set to fixed stand-ins."""
    text = _TIMING.sub(lambda m: m.group(1) + _NUMBER.sub(r"\g<1>0", m.group(2)) + m.group(3), text)
    text = re.sub(r'"started_utc":"[^"]*"', '"started_utc":"T"', text)
    return re.sub(r'"version":"[^"]*"', '"version":"V"', text)


def rounding_differences(text: str, golden: str) -> list[str]:
    """Where `text` differs from `golden` beyond floating-point rounding: any difference outside the numbers, an
    integer or a number's form (integer or decimal) that differs, or a decimal more than two units of the golden
    one's last written digit away."""
    if _WRITTEN_NUMBER.sub("#", text) != _WRITTEN_NUMBER.sub("#", golden):
        return ["the text around the numbers differs"]
    found = []
    for number, expected in zip(_WRITTEN_NUMBER.finditer(text), _WRITTEN_NUMBER.finditer(golden), strict=True):
        written, want = number.group(0), expected.group(0)
        decimals = expected.group(1)
        if decimals is None or number.group(1) is None or "e" in want:
            if written != want:
                found.append(f"{written} instead of {want}")
        elif abs(float(written) - float(want)) > 2 * 10.0 ** -len(decimals) + 1e-12:
            found.append(f"{written} instead of {want}")
    return found


def _check(name: str, text: str) -> None:
    """Compare `text` (masked) with the golden file `name` up to floating-point rounding, or write it when asked."""
    path = GOLDEN / name
    if WRITE:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    differences = rounding_differences(text, path.read_text(encoding="utf-8"))
    assert differences == [], f"{name} differs from the branchrange/v1 output it pins: {differences[:5]}"


def test_a_difference_of_rounding_passes_and_any_other_fails():
    golden = '{"x":-0.11143,"n":3,"s":"a1","d":[1.5,0.25]}'
    assert rounding_differences('{"x":-0.11142,"n":3,"s":"a1","d":[1.5,0.26]}', golden) == []
    assert rounding_differences('{"x":-0.11140,"n":3,"s":"a1","d":[1.5,0.25]}', golden) == [
        "-0.11140 instead of -0.11143"
    ]
    assert rounding_differences('{"x":-0.11143,"n":4,"s":"a1","d":[1.5,0.25]}', golden) == ["4 instead of 3"]
    assert rounding_differences('{"x":-0.11143,"n":3.0,"s":"a1","d":[1.5,0.25]}', golden) == ["3.0 instead of 3"]
    assert rounding_differences('{"x":-0.11143,"n":3,"s":"b1","d":[1.5,0.25]}', golden) != []
    assert rounding_differences('{"y":-0.11143,"n":3,"s":"a1","d":[1.5,0.25]}', golden) != []


def test_the_masking_keeps_everything_but_the_varying_values():
    line = '{"a":1.5,"timing_ms":{"rectify":0.12,"total":3e-05},"started_utc":"2024-01-01T00:00:00Z","b":[2]}'
    assert _mask_varying(line) == '{"a":1.5,"timing_ms":{"rectify":0,"total":0},"started_utc":"T","b":[2]}'


def test_demo_writes_the_v1_result_table_and_overlay_it_wrote_before(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo")]) == 0
    printed = "\n".join(
        line
        for line in capsys.readouterr().out.splitlines()
        if not line.startswith(("rendered scene", "pipeline:", "wrote", "\nwrote"))
    )
    _check("demo_result.json", _mask_varying((tmp_path / "demo" / "result.json").read_text(encoding="utf-8")))
    _check("demo_stdout.txt", printed + "\n")
    overlay = cv2.imread(str(tmp_path / "demo" / "overlay.png"))
    _check("demo_overlay.sha256", hashlib.sha256(overlay.tobytes()).hexdigest() + "\n")


def test_estimate_writes_the_v1_json_with_its_pair_check_as_before(tmp_path):
    scene = render_scene(6, SynthCamera.zed_mini(640, 360))
    write_rgb(tmp_path / "left.png", scene.left)
    write_rgb(tmp_path / "right.png", scene.right)
    write_mask(tmp_path / "mask.png", scene.instance_mask)
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "estimate",
                "--left",
                str(tmp_path / "left.png"),
                "--right",
                str(tmp_path / "right.png"),
                "--focal-px",
                str(scene.camera.focal_px),
                "--baseline-m",
                str(scene.camera.baseline_m),
                "--mask",
                str(tmp_path / "mask.png"),
                "--max-disp",
                "128",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    _check("estimate.json", _mask_varying(out.read_text(encoding="utf-8")).replace(str(tmp_path), "TMP"))


def test_replay_writes_the_v1_lines_of_a_roi_run_as_before(tmp_path):
    recording = write_tree_recording(tmp_path / "rec", 3, 500_000_000)
    config = tmp_path / "replay.toml"
    config.write_text("[stereo]\nmax_disp = 64\n")
    out = tmp_path / "results.jsonl"
    assert main(["replay", str(recording), "--out", str(out), "--config", str(config)]) == 0
    written = out.read_text(encoding="utf-8").splitlines(keepends=True)[1:]
    assert [result_line(r) for r in read_results(out)] == written  # a log read back writes the same bytes
    text = _mask_varying(out.read_text(encoding="utf-8"))
    text = re.sub(r'"config_sha256":"[^"]*"', '"config_sha256":"H"', text)
    text = re.sub(r'"source":"replay:[^"]*"', '"source":"replay:REC"', text)
    _check("replay.jsonl", text)
