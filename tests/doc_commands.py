"""The manual's runnable shell blocks: found with Sybil, run in a sandbox of small replay data.

A fenced `sh` or `bash` block of a page under `docs/` is runnable when the line before its opening fence is
the marker `<!-- runnable -->` (an HTML comment: neither GitHub nor the built site shows it), or
`<!-- runnable: needs rosbags mcap -->` for a block that needs an optional extra's modules (skipped, saying
which, where they are not installed). It runs as a
`bash -e` script in a copy of the sandbox (the data its commands name, made once per test run by
`make_sandbox`), with the test's Python environment first on PATH, so `branchrange` and `emcstereo` are the
checkout's; a non-zero exit or more than `BLOCK_TIMEOUT_S` seconds fails it, with the end of its output.
Blocks that need a camera, a network, the vehicle's own files or minutes of CPU stay unmarked; their
`branchrange` and `emcstereo` command lines are still parsed by the commands' own argument parsers
(`command_line_error`), so a missing required option or a renamed one shows without running anything.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
import subprocess
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

from sybil import Document, Example, Region
from sybil.parsers.markdown.lexers import FencedCodeBlockLexer

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
MARKER = "<!-- runnable -->"
#: The marker, with the optional extra's modules a block needs (`needs`: importable names, space-separated).
MARKER_LINE = re.compile(r"^\s*<!-- runnable(?:: needs (?P<needs>[\w. ]+?))? -->\s*$")
#: Seconds one block may run (its commands start Python, each about 2 s, on tiny data).
BLOCK_TIMEOUT_S = 60
#: Characters of a failing block's output quoted in the failure.
OUTPUT_TAIL_CHARS = 3000
SHELL_LANGUAGES = r"sh|bash"
#: The sandbox's synthetic recording: frames, WIDTHxHEIGHT (small: a replay of it takes a second).
RECORDING_FRAMES, RECORDING_SIZE = 3, "320x180"
#: The sandbox's rectified pair: the ZED Mini rig scaled to 640×360 (f = 320 px, B = 0.063 m), scene seed.
PAIR_WIDTH, PAIR_HEIGHT, PAIR_SEED = 640, 360, 9


def _marker_before(document: Document, region: Region) -> re.Match[str] | None:
    """The marker when it is the last non-blank line before the block's opening fence."""
    return MARKER_LINE.match(document.text[: region.start].rstrip().rsplit("\n", 1)[-1])


class RunnableShellParser:
    """Sybil parser: one example per marked shell block, evaluated by `run_shell_block`; the example's
    `parsed` is the block's source, and the modules it needs go to the namespace as `needs`."""

    def __init__(self) -> None:
        self.lexer = FencedCodeBlockLexer(language=SHELL_LANGUAGES)

    def __call__(self, document: Document) -> Iterable[Region]:
        for region in self.lexer(document):
            marker = _marker_before(document, region)
            if marker is not None:
                needs = tuple((marker["needs"] or "").split())
                yield Region(region.start, region.end, (region.lexemes["source"], needs), run_shell_block)


def markers_without_shell_block(text: str) -> list[int]:
    """Line numbers (1-based) of markers not followed, on the next non-blank line, by an `sh`/`bash` fence:
    a marker before a `text` block or a paragraph would silently run nothing."""
    lines = text.splitlines()
    fence = re.compile(rf"^\s*(?:[-*+]|\d+[.)])?\s*(`{{3,}}|~{{3,}})({SHELL_LANGUAGES})\s*$")
    orphans = []
    for number, line in enumerate(lines, start=1):
        if not MARKER_LINE.match(line):
            continue
        following = next((later for later in lines[number:] if later.strip()), "")
        if not fence.match(following):
            orphans.append(number)
    return orphans


def runnable_examples(pages: Iterable[Path]) -> Iterator[Example]:
    """Every marked shell block of `pages`, in page order."""
    parser = RunnableShellParser()
    for page in pages:
        yield from Document.parse(str(page), parser).examples()


def example_id(example: Example) -> str:
    """`docs/page.md:LINE`, the block's opening fence: the test's id and the place to fix."""
    path = Path(example.path)
    return f"{path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else path}:{example.line}"


def block_source(example: Example) -> str:
    """The shell commands of a runnable block, as written."""
    return str(example.parsed[0])


def modules_needed(example: Example) -> tuple[str, ...]:
    """The importable modules the block's marker says it needs (an optional extra's)."""
    return tuple(example.parsed[1])


def shell_command_lines(page: Path) -> list[tuple[int, list[str]]]:
    """(line of the block's opening fence, argv) of each `branchrange` or `emcstereo` command in every `sh`/`bash`
    block of the page, marked or not: continuation lines joined, comments dropped."""
    document = Document(page.read_text(encoding="utf-8"), str(page))
    commands = []
    for region in FencedCodeBlockLexer(language=SHELL_LANGUAGES)(document):
        line = document.text.count("\n", 0, region.start) + 1
        for command in re.sub(r"\\\n\s*", " ", region.lexemes["source"]).splitlines():
            argv = shlex.split(command, comments=True)
            if argv and argv[0] in ("branchrange", "emcstereo"):
                commands.append((line, argv))
    return commands


def command_line_error(argv: list[str]) -> str | None:
    """What the command's argument parser says about `argv` (`branchrange …` or `emcstereo …`), or None when it
    accepts it; nothing runs."""
    from branchrange.cli import COMMAND_MODULES as BRANCHRANGE_COMMANDS
    from stereo.cli import COMMAND_MODULES as EMCSTEREO_COMMANDS
    from stereo.cli import build_parser

    modules = {"branchrange": BRANCHRANGE_COMMANDS, "emcstereo": EMCSTEREO_COMMANDS}[argv[0]]
    errors = io.StringIO()
    try:
        with contextlib.redirect_stderr(errors), contextlib.redirect_stdout(io.StringIO()):
            build_parser(argv[0], "", modules).parse_args(argv[1:])
    except SystemExit as exit_:
        return errors.getvalue().strip().splitlines()[-1] if exit_.code else None
    return None


def run_shell_block(example: Example) -> None:
    """Run the block with bash -e in the directory `example.namespace["workdir"]`; raise when it fails."""
    workdir: Path = example.namespace["workdir"]
    environment = dict(os.environ)
    environment["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), environment.get("PATH", "")])
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), environment.get("PYTHONPATH")]))
    try:
        done = subprocess.run(
            ["bash", "-e", "-o", "pipefail", "-c", block_source(example)],
            cwd=workdir,
            env=environment,
            capture_output=True,
            text=True,
            timeout=BLOCK_TIMEOUT_S,
            stdin=subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired as timeout:
        raise AssertionError(f"{example_id(example)}: still running after {BLOCK_TIMEOUT_S} s") from timeout
    if done.returncode != 0:
        output = (done.stdout + done.stderr)[-OUTPUT_TAIL_CHARS:]
        raise AssertionError(f"{example_id(example)}: exit status {done.returncode}\n{output}")


def make_sandbox(root: Path) -> Path:
    """The data the marked blocks name, in `root`: `deploy/` (the repository's, linked), a synthetic recording
    `flights/2024-05-03` (`branchrange synth-flight`, with truth masks), and a rectified synthetic pair
    `L.png`, `R.png` with its instance mask `mask.png` (uint16 ids; stereo.synth)."""
    from branchrange.cli import main as branchrange
    from camera.sources.image_files import write_mask, write_rgb
    from stereo.synth import SynthCamera, render_scene

    root.mkdir(parents=True, exist_ok=True)
    (root / "deploy").symlink_to(ROOT / "deploy", target_is_directory=True)
    recording = root / "flights" / "2024-05-03"
    flight = ["--out", str(recording), "--frames", str(RECORDING_FRAMES), "--resolution", RECORDING_SIZE]
    if branchrange(["synth-flight", *flight]) != 0:
        raise RuntimeError(f"branchrange synth-flight could not write the sandbox's recording {recording}")
    scene = render_scene(PAIR_SEED, SynthCamera.zed_mini(PAIR_WIDTH, PAIR_HEIGHT))
    write_rgb(root / "L.png", scene.left)
    write_rgb(root / "R.png", scene.right)
    write_mask(root / "mask.png", scene.instance_mask)
    return root
