"""The figures the manual quotes from result files (`tools/docs_figures.py`) resolve and match their files."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from docs_figures import FigureError, drifted, figures_in, pages, render, rewrite  # noqa: E402

SEGMENTER = "benchmarks/segmenter_results.json"
LEARNED_RECALL = 'synthetic."sgbm/learned".recall'
PAGES_WITH_FIGURES = [page for page in pages() if figures_in(page, page.read_text(encoding="utf-8"))]


def _figure(path: str, shown: str, file: str = SEGMENTER, options: str = "×100 .1f") -> str:
    return f"<!-- fig {file} {path} {options} -->{shown}<!-- /fig -->"


@pytest.mark.parametrize("page", PAGES_WITH_FIGURES, ids=lambda page: page.relative_to(ROOT).as_posix())
def test_every_figure_matches_its_result_file(page: Path) -> None:
    """Each figure of the page resolves in its file and shows what the file says (fix: `python
    tools/docs_figures.py --write`)."""
    stale = drifted(page, page.read_text(encoding="utf-8"))
    assert not stale, "\n".join(
        f"{figure.where()}: shows {figure.shown}, {figure.file} says {value}" for figure, value in stale
    )


def test_the_drifted_figures_are_sourced() -> None:
    """The figures issue 49 found typed wrong are read from their files now: the int8 and @1280 segmenter rows,
    the onboard loop's truth-mask rate and the deploy files' thresholds."""
    sourced = {
        (figure.file, figure.path)
        for page in PAGES_WITH_FIGURES
        for figure in figures_in(page, page.read_text(encoding="utf-8"))
    }
    assert {
        (SEGMENTER, 'synthetic."sgbm/learned-int8".ms_per_frame'),
        (SEGMENTER, 'synthetic."sgbm/learned-int8".recall'),
        (SEGMENTER, 'synthetic."sgbm/learned@1280".ms_per_frame'),
        ("benchmarks/realtime_roi_instances.json", 'modes."roi-sgbm/truth".fresh_rate_hz'),
        ("deploy/onboard_cpu.toml", "cutpoints.target_min_confidence"),
    } <= sourced
    assert {page.name for page in PAGES_WITH_FIGURES} >= {"segmenter.md", "performance.md"}


def test_a_drifted_figure_is_found_rewritten_and_rendered(tmp_path: Path) -> None:
    """A figure typed wrong is reported with the file's value; `--write` types that value and keeps the
    comments; the built page shows the bare value."""
    page = tmp_path / "page.md"
    text = f"recall {_figure(LEARNED_RECALL, '99.9')} % a frame"
    ((figure, value),) = drifted(page, text)
    assert (figure.shown, value, figure.line) == ("99.9", "65.3", 1)
    fixed = rewrite(page, text)
    assert not drifted(page, fixed) and fixed.count("<!-- fig ") == 1
    assert render(page, fixed) == "recall 65.3 % a frame"


@pytest.mark.parametrize(
    ("figure", "message"),
    [
        (_figure("synthetic", "1", file="benchmarks/no_such_results.json"), "does not exist"),
        (_figure('synthetic."no such row".recall', "1"), "None, not a finite number"),
        (_figure('synthetic."sgbm/learned".recall_ci95', "1"), "not a finite number"),
        (_figure("synthetic.[", "1"), "not a JMESPath expression"),
        (_figure("orchard_hardware", "1", options=".1f"), "False, not a finite number"),
        (_figure("cpu", "1", options=".1f"), "'AMD EPYC.*not a finite number"),
        (_figure("cpu", "1", options="s"), "not a figure"),
        (_figure('synthetic."sgbm/learned".frames', "1", options="×100 d"), "format 'd'"),
    ],
)
def test_a_figure_that_cannot_be_read_says_why(tmp_path: Path, figure: str, message: str) -> None:
    """A missing file, a path to nothing, a list, a bad expression, a boolean, a text, a figure comment not well
    formed or a format that does not fit the number fail with the page's line and the reason (the build fails on
    it too)."""
    with pytest.raises(FigureError, match=message) as error:
        drifted(tmp_path / "page.md", f"intro\n\n{figure}\n")
    assert "page.md:3" in str(error.value)


def test_a_figure_quoted_in_a_code_span_is_text(tmp_path: Path) -> None:
    """The syntax shown right after a backtick (the contributing page explains it so) is neither read nor replaced."""
    text = f"write `{_figure(LEARNED_RECALL, '65.3')}` and `<!-- fig FILE PATH FORMAT -->TEXT<!-- /fig -->`"
    assert figures_in(tmp_path / "page.md", text) == [] and render(tmp_path / "page.md", text) == text
