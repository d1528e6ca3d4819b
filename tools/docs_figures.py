"""Figures the manual quotes from the benchmarks' JSON result files (and the deploy files' TOML settings), so that
no page can differ from its file.

A figure is written in a page's Markdown as

    <!-- fig benchmarks/segmenter_results.json synthetic."sgbm/learned".recall ×100 .1f -->65.3<!-- /fig -->

- the file, relative to the repository's root: a JSON result file, or a TOML file (`deploy/onboard.toml`);
- a JMESPath expression for the number in it (`jmespath.org`: dots between keys, a key holding `/`, `@`, `-`
  or spaces in double quotes, `[0]` for a list's first element);
- optionally `×N`, a factor (`×100`: a fraction shown in percent, the `%` sign is the page's);
- a Python format spec for the number (`.1f`, `.0f`, `,.0f`).

A figure right after a backtick (a code span quoting the syntax, as on the contributing page) is text.
Between the two comments stands the figure as the page shows it on GitHub, typed by `python
tools/docs_figures.py --write`, never by hand; the built manual (`tools/docs_hooks.py`) shows the value read
from the file at build time, and the build and `tests/test_docs_figures.py` fail when the typed figure differs
from it or when the file, the path or the number is missing. So after a benchmark writes its result file
again, `--write` updates every page that quotes it, and a figure cannot be edited away from its file.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import tomllib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import jmespath

ROOT = Path(__file__).resolve().parents[1]
#: The pages that may quote figures: the manual and the benchmark logs it serves.
PAGE_GLOBS = ("docs/**/*.md", "benchmarks/results/*.md", "benchmarks/RESULTS.md")
FIGURE = re.compile(
    r"(?<!`)<!--\s*fig\s+(?P<file>\S+)\s+(?P<path>.+?)(?:\s+×(?P<factor>[0-9.]+))?\s+(?P<spec>[,_]?(?:\.\d+)?[dfeg%])\s*-->"
    r"(?P<shown>.*?)<!--\s*/fig\s*-->"
)
#: Where a figure starts, well formed or not.
FIGURE_START = re.compile(r"(?<!`)<!--\s*fig\s")


class FigureError(ValueError):
    """A figure's file, path or number cannot be read, or its format spec does not format it."""


@dataclass(frozen=True)
class Figure:
    """One figure of a page: where it is, what it reads, and what the page shows now."""

    page: Path
    line: int
    file: str
    path: str
    factor: float | None
    spec: str
    shown: str

    def where(self) -> str:
        """`page.md:LINE` relative to the repository, for messages."""
        page = self.page.relative_to(ROOT) if self.page.is_relative_to(ROOT) else self.page
        return f"{page.as_posix()}:{self.line}"


@cache
def _result_file(file: str) -> Any:
    """The parsed JSON or TOML (by its suffix) of a result file (read once per process; `file` relative to the
    repository)."""
    path = ROOT / file
    if not path.is_file():
        raise FigureError(f"result file {file} does not exist")
    text = path.read_text(encoding="utf-8")
    try:
        return tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as error:
        raise FigureError(f"result file {file} cannot be parsed: {error}") from error


def _figure_of(page: Path, text: str, match: re.Match[str]) -> Figure:
    """The Figure a regex match stands for."""
    return Figure(
        page=page,
        line=text.count("\n", 0, match.start()) + 1,
        file=match["file"],
        path=match["path"],
        factor=float(match["factor"]) if match["factor"] else None,
        spec=match["spec"],
        shown=match["shown"],
    )


def _check_syntax(page: Path, text: str) -> None:
    """`FigureError` for a figure comment that is not well formed (it would otherwise be left as it is)."""
    starts = {match.start() for match in FIGURE.finditer(text)}
    for start in FIGURE_START.finditer(text):
        if start.start() not in starts:
            line = text.count("\n", 0, start.start()) + 1
            raise FigureError(
                f"{Figure(page, line, '', '', None, '', '').where()}: not a figure: write "
                "<!-- fig FILE PATH [×N] FORMAT -->TEXT<!-- /fig --> on one line (FORMAT as .1f, .0f, d)"
            )


def figures_in(page: Path, text: str) -> list[Figure]:
    """Every figure of a page's Markdown, in order; `FigureError` for one that is not well formed."""
    _check_syntax(page, text)
    return [_figure_of(page, text, match) for match in FIGURE.finditer(text)]


def value_of(figure: Figure) -> str:
    """The figure as its result file says it, formatted: `FigureError` saying why when it cannot be."""
    try:
        found = jmespath.search(figure.path, _result_file(figure.file))
    except jmespath.exceptions.JMESPathError as error:
        raise FigureError(f"{figure.where()}: {figure.path!r} is not a JMESPath expression: {error}") from error
    except FigureError as error:
        raise FigureError(f"{figure.where()}: {error}") from error
    if isinstance(found, bool) or not isinstance(found, int | float) or not math.isfinite(found):
        raise FigureError(f"{figure.where()}: {figure.path} in {figure.file} is {found!r}, not a finite number")
    try:
        return format(found if figure.factor is None else found * figure.factor, figure.spec)
    except ValueError as error:
        raise FigureError(f"{figure.where()}: format {figure.spec!r}: {error}") from error


def render(page: Path, text: str) -> str:
    """The page's Markdown with each figure replaced by its value from its result file (the built manual)."""
    _check_syntax(page, text)
    return FIGURE.sub(lambda match: value_of(_figure_of(page, text, match)), text)


def drifted(page: Path, text: str) -> list[tuple[Figure, str]]:
    """The figures whose typed text differs from their result file's value, with that value."""
    return [(figure, value) for figure in figures_in(page, text) if (value := value_of(figure)) != figure.shown]


def rewrite(page: Path, text: str) -> str:
    """The page's Markdown with each figure's typed text set to its result file's value (comments kept)."""

    def typed(match: re.Match[str]) -> str:
        value = value_of(_figure_of(page, text, match))
        return match[0][: match.start("shown") - match.start()] + value + match[0][match.end("shown") - match.start() :]

    _check_syntax(page, text)
    return FIGURE.sub(typed, text)


def pages() -> list[Path]:
    """The Markdown files that may quote figures."""
    return sorted({path for pattern in PAGE_GLOBS for path in ROOT.glob(pattern)})


def main(argv: list[str] | None = None) -> int:
    """Check (exit 1 on a drifted or unreadable figure) or, with `--write`, update the figures of the pages."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="type each figure's value from its result file")
    arguments = parser.parse_args(argv)
    problems = 0
    for page in pages():
        text = page.read_text(encoding="utf-8")
        try:
            if arguments.write:
                updated = rewrite(page, text)
                if updated != text:
                    page.write_text(updated, encoding="utf-8")
                    print(f"updated {page.relative_to(ROOT)}")
                continue
            for figure, value in drifted(page, text):
                print(f"{figure.where()}: shows {figure.shown!r}, {figure.file} says {value!r}")
                problems += 1
        except FigureError as error:
            print(error, file=sys.stderr)
            problems += 1
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
