"""The manual and the README keep their promises: every error type and every warning or error the code logs
is explained on the troubleshooting page, the README stays short with its two commands, and its links lead
somewhere.

The rules, both over the code of `branchrange/`, `camera/`, `stereo/` and `api/`, read with `ast` (no module,
and no heavy dependency, is imported):
- an error type is a class that derives, directly or through another such class, from a built-in exception
  or warning; each has a table row of its own (`module.Class`, cause, fix);
- a logged message is the format string of a `log.warning`, `log.error` or `log.exception` call (also
  `(log.warning if … else log.info)(…)`); every literal piece of it between the %-placeholders is quoted on
  the page, where the placeholders are written `…`.
"""

from __future__ import annotations

import ast
import builtins
import re
from functools import cache
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
LOGGED_LEVELS = frozenset({"warning", "error", "exception"})
#: A %-placeholder of a logging format string (`%d`, `%.1f`, `%r`, …).
PLACEHOLDER = re.compile(r"%[-#0 +]*\d*(?:\.\d+)?[sdrfigx]")


def _base_name(node: ast.expr) -> str:
    """`ValueError` for `ValueError`, `SourceError` for `frame.SourceError`; '' for anything else."""
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


@cache
def _modules() -> list[tuple[str, ast.Module]]:
    """(dotted module name, parsed source) of every Python file of PACKAGES; parsed once per test run."""
    modules = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            modules.append((name, ast.parse(path.read_text(encoding="utf-8"))))
    return modules


def _logs_at_user_level(func: ast.expr) -> bool:
    """`log.warning`, `log.error`, `log.exception`, or a conditional choosing one of them."""
    if isinstance(func, ast.IfExp):
        return _logs_at_user_level(func.body) or _logs_at_user_level(func.orelse)
    return isinstance(func, ast.Attribute) and func.attr in LOGGED_LEVELS and _base_name(func.value) == "log"


def logged_messages() -> list[str]:
    """The format strings of the warnings and errors the packages log."""
    messages = set()
    for _, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and _logs_at_user_level(node.func) and node.args:
                first = node.args[0]
                if isinstance(first, ast.Constant) and isinstance(first.value, str):
                    messages.add(first.value)
    return sorted(messages)


def user_facing_errors() -> list[str]:
    """Dotted names (`camera.calibration.CalibrationError`) of the exception and warning classes of PACKAGES."""
    classes = [
        (module, node.name, [_base_name(base) for base in node.bases])
        for module, tree in _modules()
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
    ]
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


def test_logged_messages_are_found() -> None:
    """The scan sees the daemon's late-result, camera-lost and link messages."""
    messages = logged_messages()
    assert "camera disconnected: %s" in messages
    assert any(message.startswith("frame took %.0f ms") for message in messages)
    assert any(message.startswith("no vehicle state from the autopilot") for message in messages)  # IfExp form


@pytest.mark.parametrize("message", logged_messages())
def test_every_logged_message_is_quoted_in_troubleshooting(message: str) -> None:
    """Each warning or error the code logs is on the troubleshooting page, placeholders written `…`."""
    page = TROUBLESHOOTING.read_text(encoding="utf-8")
    missing = [piece.strip() for piece in PLACEHOLDER.split(message) if piece.strip() and piece.strip() not in page]
    assert not missing, f"{message!r}: not on {TROUBLESHOOTING.relative_to(ROOT)}: {missing}"


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
