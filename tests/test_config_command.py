"""`branchrange config check|show|schema|reference`: every problem with its key and line, the suggestion for a
mistyped name, the exit codes, and each effective value's source (default, file, --set)."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import pytest

from branchrange.cli import main
from branchrange.commands.exit_codes import BAD_INPUT, DONE
from branchrange.config.check import check_config, key_lines
from branchrange.config.loader import config_from_dict, load_config
from branchrange.config.schema import SCHEMA_PATH
from branchrange.core.settings_check import ConfigError

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"

MISTYPED = """\
#:schema ../schema.json

[stereo]
backend = "sgbm"     # fine
max_disp = 100       # not a multiple of 16

[cutpoints]
cut_offset_m = 0.05
target_min_confidnce = 0.7

[segmenter.structure]
min_range_m = 2.0
max_range_m = 1.0    # below min_range_m: only the class's checks know

[mavlnk]
url = "/dev/ttyTHS1"
"""


@pytest.fixture
def mistyped(tmp_path: Path) -> Path:
    path = tmp_path / "drone.toml"
    path.write_text(MISTYPED, encoding="utf-8")
    return path


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    status = main(["config", *argv])
    out, err = capsys.readouterr()
    return status, out, err


def test_key_lines_finds_tables_keys_and_sub_tables():
    lines = key_lines(MISTYPED)
    assert lines["stereo"] == 3 and lines["stereo.max_disp"] == 5
    assert lines["cutpoints.target_min_confidnce"] == 9
    assert lines["segmenter.structure"] == 11 and lines["segmenter.structure.max_range_m"] == 13
    assert lines["mavlnk.url"] == 16 and "backend" not in lines  # a key belongs to its table
    dotted = key_lines('stereo.backend = "sgbm"\n[segmenter]\nstructure . max_range_m = 3\n')
    assert dotted == {"stereo.backend": 1, "segmenter": 2, "segmenter.structure.max_range_m": 3}


def test_check_prints_every_problem_with_its_line_and_the_nearest_name(capsys, mistyped):
    status, out, err = run(capsys, "check", str(mistyped))
    assert status == BAD_INPUT and "3 problems" in err
    lines = out.splitlines()
    assert lines[0].startswith(f"{mistyped}:5: stereo.max_disp: 100 is not a multiple of 16")
    assert lines[1].startswith(f"{mistyped}:9: cutpoints.target_min_confidnce: unknown option")
    assert lines[1].endswith("did you mean `target_min_confidence`?")
    assert lines[2].startswith(f"{mistyped}:15: [mavlnk]: unknown section") and lines[2].endswith("`mavlink`?")
    assert len(lines) == 3  # the checks between keys wait until the schema passes


def test_check_runs_the_checks_between_keys_once_the_schema_passes(capsys, tmp_path):
    path = tmp_path / "range.toml"
    path.write_text("[segmenter.structure]\nmin_range_m = 2.0\nmax_range_m = 1.0\n")
    status, out, _ = run(capsys, "check", str(path))
    assert status == BAD_INPUT
    assert out.startswith(f"{path}:3: segmenter.structure.max_range_m = 1.0: expected > min_range_m (2.0 m)")


def test_check_marks_what_came_from_set(capsys):
    status, out, _ = run(capsys, "check", str(DEPLOY / "serve.toml"), "--set", "api.prot=8081")
    assert status == BAD_INPUT
    assert out.startswith("--set: api.prot: unknown option") and out.rstrip().endswith("did you mean `port`?")
    status, out, _ = run(capsys, "check", str(DEPLOY / "serve.toml"), "--set", "stereo.max_disp")
    assert status == BAD_INPUT and out.startswith("--set: --set 'stereo.max_disp': expected SECTION.KEY=VALUE")


@pytest.mark.parametrize("path", sorted(DEPLOY.glob("*.toml")), ids=lambda p: p.name)
def test_check_passes_every_deploy_file_and_counts_its_keys(capsys, path):
    # the file alone: what it names on the drone is not on this machine (tests/test_config_needs.py installs it)
    status, out, _ = run(capsys, "check", str(path), "--file-only")
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    count = sum(len([v for v in t.values() if not isinstance(v, dict)]) for t in data.values())
    count += sum(len(s) for t in data.values() for s in t.values() if isinstance(s, dict))
    assert (status, out) == (DONE, f"OK: {path} ({count} keys)\n")


@pytest.mark.parametrize(
    "text, message",
    [
        (None, "configuration file not found"),
        (
            "x = 1\n[stereo\nbackend = 1\n",
            "not valid TOML (Expected ']' at the end of a table declaration (at line 2, column 8))",
        ),
        (b'[stereo]\nbackend = "\xff"\n', "not UTF-8 text (invalid start byte at byte 20)"),
    ],
)
def test_check_refuses_a_file_it_cannot_read_without_a_traceback(capsys, tmp_path, text, message):
    path = tmp_path / "bad.toml"
    if isinstance(text, bytes):
        path.write_bytes(text)
    elif text is not None:
        path.write_text(text)
    status, out, _ = run(capsys, "check", str(path))
    where = f"{path}:2" if "at line 2" in message else str(path)  # a syntax error's line, from tomllib
    assert (status, out) == (BAD_INPUT, f"{where}: {message}\n")


def test_show_gives_each_value_and_its_source(capsys, tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[stereo]\nmax_disp = 64\nmode = "full"\n[api]\ntoken = "s3cret"\n')
    status, out, _ = run(capsys, "show", str(path), "--set", "stereo.max_disp=128", "--json")
    shown = json.loads(out)
    assert status == DONE
    assert shown["stereo.max_disp"] == {"value": 128, "source": "--set"}  # --set wins over the file
    assert shown["stereo.mode"] == {"value": "full", "source": "file"}
    assert shown["stereo.backend"] == {"value": "sgbm", "source": "default"}
    assert shown["camera.mount_xyz_m"] == {"value": [0.0, 0.0, 0.0], "source": "default"}
    assert shown["api.token"] == {"value": "(set, hidden)", "source": "file"}  # a secret is never echoed
    assert "s3cret" not in out


def test_show_as_toml_reads_back_as_the_same_configuration(capsys):
    status, out, _ = run(capsys, "show", str(DEPLOY / "onboard.toml"), "--set", "segmenter.structure.max_range_m=3.5")
    assert status == DONE
    assert re.search(r'^source = "zed:/dev/zedmini:HD720" +# file$', out, re.MULTILINE)
    assert re.search(r"^max_range_m = 3\.5 +# --set$", out, re.MULTILINE)
    shown = tomllib.loads(out)  # every value followed by its source as a comment: still TOML
    expected = load_config(DEPLOY / "onboard.toml", [("segmenter.structure.max_range_m", 3.5)])
    assert config_from_dict(shown) == expected


def test_show_refuses_a_bad_file_like_check(capsys, mistyped):
    status, out, _ = run(capsys, "show", str(mistyped))
    assert status == BAD_INPUT and "did you mean `target_min_confidence`?" in out


def test_schema_and_reference_print_the_shipped_files(capsys):
    status, out, _ = run(capsys, "schema")
    assert status == DONE and out == SCHEMA_PATH.read_text(encoding="utf-8")
    status, out, _ = run(capsys, "reference")
    assert status == DONE and out == (DEPLOY.parent / "docs" / "configuration.md").read_text(encoding="utf-8")


def test_the_loader_suggests_the_nearest_name_too():
    """What the daemon says on the drone when a key is mistyped (it stops at the first error)."""
    with pytest.raises(
        ConfigError, match=r"cutpoints\.target_min_confidnce: .*; did you mean `target_min_confidence`\?$"
    ):
        config_from_dict({"cutpoints": {"target_min_confidnce": 0.7}})
    with pytest.raises(ConfigError, match=r"\[mavlnk\]: unknown section; .*; did you mean `mavlink`\?$"):
        config_from_dict({"mavlnk": {}})
    with pytest.raises(ConfigError, match=r"api\.zzz: unknown option; \[api\] takes [a-z_, ]+$"):  # nothing near
        config_from_dict({"api": {"zzz": 1}})


def test_check_config_gives_the_effective_configuration_when_valid():
    result = check_config(DEPLOY / "serve.toml", [("stereo.max_disp", 128)])
    assert result.problems == [] and result.config == load_config(DEPLOY / "serve.toml", [("stereo.max_disp", 128)])
    assert result.sources["stereo.max_disp"] == "--set" and result.sources["api.host"] == "file"


def test_check_names_a_folder_given_for_the_file(capsys, tmp_path):
    status, out, _ = run(capsys, "check", str(tmp_path))
    assert (status, out) == (BAD_INPUT, f"{tmp_path}: cannot be read (Is a directory)\n")


def test_show_without_a_file_gives_the_defaults_and_the_set_keys(capsys):
    status, out, _ = run(capsys, "show", "--set", "tracking.gate_m=0.2", "--json")
    shown = json.loads(out)
    assert status == DONE and shown["tracking.gate_m"] == {"value": 0.2, "source": "--set"}
    assert {s["source"] for key, s in shown.items() if key != "tracking.gate_m"} == {"default"}
    status, out, err = run(capsys, "show", "--set", "cutpoints.min_range_m=20")  # beyond max_range_m (10)
    assert status == BAD_INPUT and out.startswith(
        "--set: cutpoints.min_range_m = 20 conflicts with cutpoints.max_range_m"
    )
    assert err == "the defaults with --set: 1 problem\n"
