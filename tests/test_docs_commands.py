"""Every shell block of the manual marked `<!-- runnable -->` runs and exits 0 on small replay data
(`tests/doc_commands.py` says how a block is marked and run)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from doc_commands import (
    DOCS,
    MARKER,
    block_source,
    command_line_error,
    example_id,
    make_sandbox,
    markers_without_shell_block,
    modules_needed,
    runnable_examples,
    shell_command_lines,
)
from sybil import Example

PAGES = sorted(DOCS.rglob("*.md"))
EXAMPLES = list(runnable_examples(PAGES))


@pytest.fixture(scope="session")
def docs_sandbox(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The data the runnable blocks name, made once per test run."""
    return make_sandbox(tmp_path_factory.mktemp("docs-sandbox") / "sandbox")


def run_in_copy(example: Example, sandbox: Path, workdir: Path) -> None:
    """Evaluate `example` in a fresh copy of the sandbox (a block's outputs never meet another's)."""
    shutil.copytree(sandbox, workdir, symlinks=True)
    example.namespace["workdir"] = workdir
    example.evaluate()


@pytest.mark.parametrize("example", EXAMPLES, ids=example_id)
def test_runnable_block_exits_zero(example: Example, docs_sandbox: Path, tmp_path: Path) -> None:
    """The block runs as a reader would paste it, in a directory holding the data it names."""
    for module in modules_needed(example):
        pytest.importorskip(module, reason=f"{example_id(example)} needs {module} (an optional extra)")
    run_in_copy(example, docs_sandbox, tmp_path / "work")


def test_the_runnable_blocks_are_found() -> None:
    """The scan sees the replay, synthetic-flight and estimate blocks (a broken scan would pass vacuously)."""
    pages = {Path(example.path).name for example in EXAMPLES}
    assert {"recordings.md", "synthetic.md", "getting-started.md", "ros-foxglove.md"} <= pages
    assert len(EXAMPLES) >= 5


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(DOCS).as_posix())
def test_every_marker_opens_a_shell_block(page: Path) -> None:
    """A marker stands right before an `sh`/`bash` fence: elsewhere it would mark nothing."""
    orphans = markers_without_shell_block(page.read_text(encoding="utf-8"))
    assert not orphans, f"{page.name}: {MARKER} not followed by a ```sh block at lines {orphans}"


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(DOCS).as_posix())
def test_every_command_line_of_a_shell_block_parses(page: Path) -> None:
    """Each `branchrange`/`emcstereo` command of the page's shell blocks, runnable or not (a camera, a network,
    minutes of CPU), has the options its parser requires and no unknown one."""
    errors = [
        (line, " ".join(argv), error) for line, argv in shell_command_lines(page) if (error := command_line_error(argv))
    ]
    assert not errors, "\n".join(
        f"{page.name}, block at line {line}: {command}\n  {error}" for line, command, error in errors
    )


def test_a_command_line_missing_a_required_option_is_reported(tmp_path: Path) -> None:
    """The old docs' replay without --out is caught without running it; a complete one and a comment pass."""
    page = tmp_path / "page.md"
    page.write_text(
        "```sh\nbranchrange replay flights/x \\\n    --summary   # no --out\nbranchrange replay x --out r.jsonl\n```\n",
        encoding="utf-8",
    )
    commands = shell_command_lines(page)
    assert commands == [
        (1, ["branchrange", "replay", "flights/x", "--summary"]),
        (1, ["branchrange", "replay", "x", "--out", "r.jsonl"]),
    ]
    assert "required: --out" in (command_line_error(commands[0][1]) or "")
    assert command_line_error(commands[1][1]) is None
    assert "invalid choice" in (command_line_error(["emcstereo", "no-such-command"]) or "")


def test_a_failing_block_fails(tmp_path: Path, docs_sandbox: Path) -> None:
    """A block whose command fails (here: replay without its required --out, the old docs' mistake) raises,
    naming the page and line and quoting the command's error."""
    page = tmp_path / "page.md"
    page.write_text(f"Intro.\n\n{MARKER}\n```sh\nbranchrange replay flights/2024-05-03\n```\n", encoding="utf-8")
    (example,) = runnable_examples([page])
    with pytest.raises(AssertionError, match=r"exit status 2[\s\S]*--out"):
        run_in_copy(example, docs_sandbox, tmp_path / "work")


def test_unmarked_blocks_are_not_run(tmp_path: Path) -> None:
    """Only the marked blocks of a page are examples, with the modules their marker needs; a `text` block
    after a marker is reported."""
    text = (
        f"```sh\nexit 1\n```\n\n{MARKER}\n```bash\ntrue\n```\n\n{MARKER}\n```text\nnot a command\n```\n\n"
        "<!-- runnable: needs rosbags mcap -->\n```sh\nbranchrange bag-from-recording\n```\n"
    )
    page = tmp_path / "page.md"
    page.write_text(text, encoding="utf-8")
    examples = list(runnable_examples([page]))
    assert [block_source(example) for example in examples] == ["true\n", "branchrange bag-from-recording\n"]
    assert [modules_needed(example) for example in examples] == [(), ("rosbags", "mcap")]
    assert markers_without_shell_block(text) == [10]
