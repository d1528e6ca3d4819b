"""CHANGELOG.md keeps the Keep a Changelog shape, and the package's version agrees with it."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RELEASE = re.compile(r"^## \[(\d+)\.(\d+)\.(\d+)\] - (\d{4}-\d{2}-\d{2})$")


def version_headings() -> list[str]:
    return [line for line in (ROOT / "CHANGELOG.md").read_text(encoding="utf-8").splitlines() if line.startswith("## ")]


def test_unreleased_comes_first_then_releases_newest_first_with_their_dates():
    first, *released = version_headings()
    assert first == "## [Unreleased]"
    matches = [RELEASE.match(line) for line in released]
    assert released and all(matches), released
    versions = [tuple(int(part) for part in m.groups()[:3]) for m in matches]
    dates = [m.group(4) for m in matches]
    assert versions == sorted(versions, reverse=True) and dates == sorted(dates, reverse=True)


def test_the_package_version_is_the_next_release_named_under_unreleased():
    """pyproject.toml (what `--version` prints) is ahead of the newest release while changes wait under [Unreleased]."""
    version = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    newest = RELEASE.match(version_headings()[1])
    assert newest is not None
    assert tuple(int(part) for part in version.split(".")) > tuple(int(part) for part in newest.groups()[:3])
    unreleased = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8").split("## [Unreleased]")[1].split("\n## ")[0]
    assert f"The next release is {version}" in unreleased


def test_each_section_uses_keep_a_changelog_change_types():
    kinds = {
        line[4:] for line in (ROOT / "CHANGELOG.md").read_text(encoding="utf-8").splitlines() if line.startswith("### ")
    }
    assert kinds and kinds <= {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}
