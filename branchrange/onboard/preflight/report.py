"""What a preflight check found: `CheckResult` (one check) and `PreflightReport` (all of them, as text or JSON)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

PASS, FAIL, SKIP = "pass", "fail", "skip"


@dataclass(frozen=True)
class CheckResult:
    """One check: its `name`, `status` (pass, fail, or skip when an earlier failure or the configuration
    leaves nothing to check), what it `found`, and the `fix`: one sentence the operator can act on
    (empty when it passed)."""

    name: str
    status: str
    found: str
    fix: str = ""

    @classmethod
    def passed(cls, name: str, found: str) -> CheckResult:
        return cls(name, PASS, found)

    @classmethod
    def failed(cls, name: str, found: str, fix: str) -> CheckResult:
        return cls(name, FAIL, found, fix)

    @classmethod
    def skipped(cls, name: str, why: str) -> CheckResult:
        return cls(name, SKIP, why)

    def to_dict(self) -> dict[str, str]:
        """Plain-JSON view."""
        return {"name": self.name, "status": self.status, "found": self.found, "fix": self.fix}


@dataclass(frozen=True)
class PreflightReport:
    """Every check in the order it ran; ready to arm only when none failed."""

    checks: tuple[CheckResult, ...]

    @property
    def ready(self) -> bool:
        """Whether no check failed (a skipped one only follows a failure or a link turned off)."""
        return all(check.status != FAIL for check in self.checks)

    @property
    def failures(self) -> list[CheckResult]:
        """The checks that failed, in order."""
        return [check for check in self.checks if check.status == FAIL]

    def to_dict(self) -> dict[str, Any]:
        """The `--json` report."""
        return {
            "ready": self.ready,
            "failed": len(self.failures),
            "checks": [check.to_dict() for check in self.checks],
        }

    def text(self) -> str:
        """The report for a terminal: a line a check (its fix indented below a failure), then the verdict."""
        lines = []
        for check in self.checks:
            lines.append(f"{check.status.upper():4}  {check.name}: {check.found}")
            if check.fix:
                lines.append(f"      fix: {check.fix}")
        verdict = "ready to arm" if self.ready else f"NOT ready to arm: {len(self.failures)} check(s) failed"
        lines.append(f"preflight: {verdict}")
        return "\n".join(lines)
