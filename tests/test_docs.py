"""The manual and the README keep their promises: every error type a user can meet is explained on the
troubleshooting page, the README stays short with its two commands, and its links lead somewhere.

The rule for "every error type": each class defined in `branchrange/`, `camera/`, `stereo/` or `api/` that
derives, directly or through another such class, from a built-in exception or warning. Classes are read
from the source with `ast`, so no module (and no heavy dependency) is imported.
"""

from __future__ import annotations

import ast
import builtins
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("branchrange", "camera", "stereo", "api")
TROUBLESHOOTING = ROOT / "docs" / "troubleshooting.md"
README = ROOT / "README.md"
README_MAX_LINES = 150
#: Markdown files outside docs/ whose relative links must resolve in the repository.
LINKED_FILES = (README, ROOT / "benchmarks" / "RESULTS.md", *sorted((ROOT / "benchmarks" / "results").glob("*.md")))
BUILTIN_EXCEPTIONS = frozenset(
    name for name, value in vars(builtins).items() if isinstance(value, type) and issubclass(value, BaseException)
)
LINK = re.compile(r"\]\(([^)\s]+)\)")
#: A table's cell border: a pipe outside code spans (followed by an even number of backticks on its line).
CELL_BORDER = re.compile(r"\|(?=(?:[^`]*`[^`]*`)*[^`]*$)")


def _base_name(node: ast.expr) -> str:
    """`ValueError` for `ValueError`, `SourceError` for `frame.SourceError`; '' for anything else."""
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def user_facing_errors() -> list[str]:
    """Dotted names (`camera.calibration.CalibrationError`) of the exception and warning classes of PACKAGES."""
    classes: list[tuple[str, str, list[str]]] = []  # (module, class, base names)
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.ClassDef):
                    classes.append((module, node.name, [_base_name(base) for base in node.bases]))
    known = set(BUILTIN_EXCEPTIONS)
    errors: set[str] = set()
    grew = True
    while grew:  # a class derived from an error class of ours is an error class too
        grew = False
        for module, name, bases in classes:
            if f"{module}.{name}" not in errors and known.intersection(bases):
                errors.add(f"{module}.{name}")
                known.add(name)
                grew = True
    return sorted(errors)


def troubleshooting_rows() -> dict[str, list[str]]:
    """Table rows of the troubleshooting page by their first cell's code span: `name` → the row's cells."""
    rows = {}
    for line in TROUBLESHOOTING.read_text(encoding="utf-8").splitlines():
        cells = [cell.strip() for cell in CELL_BORDER.split(line.strip())[1:-1]]
        if cells and cells[0].startswith("`") and cells[0].endswith("`"):
            rows[cells[0].strip("`")] = cells
    return rows


def test_error_classes_are_found() -> None:
    """The scan sees the errors it is meant to see (a broken scan would make the next test pass vacuously)."""
    errors = user_facing_errors()
    assert "camera.calibration.FrameSizeError" in errors  # derived from one of ours, not from a built-in
    assert "stereo.backends.UntrainedModelWarning" in errors  # a warning, defined in a package's __init__
    assert "branchrange.core.pair_check.PairRefusedError" in errors
    assert len(errors) >= 40


@pytest.mark.parametrize("error", user_facing_errors())
def test_every_error_class_is_explained_in_troubleshooting(error: str) -> None:
    """Each error type has a row of its own on the troubleshooting page, with a cause and a fix."""
    row = troubleshooting_rows().get(error)
    assert row is not None, f"{error} has no row in {TROUBLESHOOTING.relative_to(ROOT)} (| `{error}` | cause | fix |)"
    assert len(row) >= 3 and all(row[1:]), f"{error}: the row needs a cause and a fix, got {row}"


def test_readme_is_short_and_keeps_its_two_commands() -> None:
    """The README stays a front page (≤ 150 lines) whose quick start is `make demo` and `make test`."""
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; at most {README_MAX_LINES}"
    commands = [line.split("#")[0].strip() for line in lines]
    assert "make demo" in commands and "make test" in commands


@pytest.mark.parametrize("document", LINKED_FILES, ids=lambda path: str(path.relative_to(ROOT)))
def test_relative_links_resolve(document: Path) -> None:
    """Every relative link of the README and the benchmark logs names a file or folder of the repository."""
    broken = []
    for target in LINK.findall(document.read_text(encoding="utf-8")):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue  # a URL or an anchor on the same page
        if not (document.parent / target.split("#")[0]).exists():
            broken.append(target)
    assert not broken, f"{document.relative_to(ROOT)}: links to missing files: {broken}"
