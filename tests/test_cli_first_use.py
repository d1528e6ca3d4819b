"""First use of both commands: `--version`, a one-line description for every subcommand, and
`emcstereo export` refusing to write random weights unless asked."""

from __future__ import annotations

import argparse

import pytest

from branchrange.cli import COMMAND_MODULES as APP_MODULES
from branchrange.cli import main as branchrange_main
from stereo.cli import COMMAND_MODULES as NET_MODULES
from stereo.cli import build_parser, package_version
from stereo.cli import main as emcstereo_main


@pytest.mark.parametrize(("prog", "main"), [("branchrange", branchrange_main), ("emcstereo", emcstereo_main)])
def test_version_flag_prints_the_package_version(prog, main, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"{prog} {package_version()}"
    assert package_version()[0].isdigit()


def _subcommands(parser: argparse.ArgumentParser, path: str = ""):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help for choice in action._choices_actions}
            for name, sub in action.choices.items():
                yield f"{path} {name}".strip(), helps.get(name)
                yield from _subcommands(sub, f"{path} {name}")


@pytest.mark.parametrize(("prog", "modules"), [("branchrange", APP_MODULES), ("emcstereo", NET_MODULES)])
def test_every_subcommand_has_a_one_line_description(prog, modules):
    found = list(_subcommands(build_parser(prog, "x", modules)))
    assert len(found) >= len(modules)
    for name, text in found:
        assert text and "\n" not in text and len(text) <= 100, f"{prog} {name}: help {text!r}"


def test_export_without_weights_is_refused_unless_random_weights_is_asked(tmp_path, capsys):
    out = tmp_path / "x.onnx"
    assert emcstereo_main(["export", "--onnx", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("emcstereo export: error: no --weights given") and "--random-weights" in err
    assert not out.exists()
    assert emcstereo_main(["export", "--onnx", str(out), "--weights", "w.pth", "--random-weights"]) == 2
    assert "exclude each other" in capsys.readouterr().err
