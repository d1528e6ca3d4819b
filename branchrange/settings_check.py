"""Range checks of frozen settings dataclasses, one message format for every branchrange section."""
from __future__ import annotations


def check_settings(section: str, settings: object, checks: dict[str, tuple[bool, str]],
                   error: type[ValueError]) -> None:
    """Raise `error` for the first failed check, naming `section.key`, its value and what was expected.

    `checks` maps a field name of `settings` to (passed, expectation), e.g.
    `{"gate_m": (self.gate_m > 0, "> 0 m")}`; called from a dataclass's `__post_init__`.
    """
    for key, (ok, expected) in checks.items():
        if not ok:
            raise error(f"{section}.{key} = {getattr(settings, key)!r}: expected {expected}")
