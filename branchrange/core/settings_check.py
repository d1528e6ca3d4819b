"""Checks of settings where they enter: the one validator of the settings dataclasses (`Settings`),
and the one table of physical ranges (baseline, focal length, image size, depth) that the API
request, the CLI options (`estimate`, `demo`) and the TOML configuration all validate against.

Every settings dataclass — one per TOML section (`branchrange.config.loader.Config` gathers them) — extends `Settings`:
it names its `section` and lists its range checks in `checks()`; constructing it runs them, so
a value from a file, from `--set`, from a command-line flag or from Python is checked by the same
rule and refused with the same message: `cutpoints.min_points = 1: expected ≥ 3 points`.

A subclass also declares the plain part of those ranges as data, `limits` (`Limit`: bounds or the
accepted values), from which `branchrange.config.schema` writes the JSON Schema that editors
complete and check the TOML with. `checks()` stays the rule that refuses a value, with its message
and the ranges that depend on other keys; tests/test_config_schema.py probes that every `Limit`
agrees with it, so the schema cannot promise what the loader refuses, or the reverse.

Why ranges and not only "> 0": the cut-point maths multiplies and divides by these values
(`Z = f·B / d`), so 1e300 overflows and 1e-320 divides by (almost) zero; a value outside what a
stereo camera on a drone can be is refused with the value and the accepted range, once, at the
entry, so nothing downstream has to guard against it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from camera.calibration import MAX_IMAGE_SIDE_PX, require_image_size

#: A settings dataclass's range checks: field name → (passed, what is expected).
Checks = dict[str, tuple[bool, str]]


class SettingsError(ValueError):
    """A setting outside what it accepts; the message names `section.key`, the value and what is accepted."""


class ConfigError(SettingsError):
    """A configuration file or value that cannot be used; the message names the key at fault."""


def one_of(choices: Iterable[str]) -> str:
    """'a', 'b' or 'c' — the accepted values of a setting, for messages."""
    quoted = [repr(c) for c in choices]
    return ", ".join(quoted[:-1]) + f" or {quoted[-1]}" if len(quoted) > 1 else quoted[0]


def check_settings(section: str, settings: object, checks: Checks, error: type[ValueError]) -> None:
    """Raise `error` for the first failed check, naming `section.key`, its value and what was expected.

    `checks` maps a field name of `settings` to (passed, expectation), e.g.
    `{"gate_m": (self.gate_m > 0, "> 0 m")}`.
    """
    for key, (ok, expected) in checks.items():
        if not ok:
            raise error(f"{section}.{key} = {getattr(settings, key)!r}: expected {expected}")


@dataclass(frozen=True)
class Limit:
    """The plain range of one setting, stated once: bounds for a number (or for each item of a list of numbers)
    or the accepted values, and `expected`, what the refusal says is accepted (`"0..64 px"`). Constructing a
    `Settings` subclass refuses a value outside it; `as_schema` states it in the generated JSON Schema; its
    meaning is the class docstring's bullet and its unit the key's suffix (`branchrange.config.schema`)."""

    minimum: float | None = None
    maximum: float | None = None
    exclusive_minimum: float | None = None
    exclusive_maximum: float | None = None
    multiple_of: int | None = None
    enum: tuple[Any, ...] = ()
    expected: str = ""

    @classmethod
    def physical(cls, quantity: str, expected: str = "") -> Limit:
        """The closed interval of `PHYSICAL_RANGES[quantity]` (`in_physical_range`'s rule)."""
        accepted = PHYSICAL_RANGES[quantity]
        return cls(minimum=accepted.low, maximum=accepted.high, expected=expected or accepted.describe())

    def admits(self, value: Any) -> bool:
        """Whether `value` (a number, a string, or a tuple of numbers: each item) is within this limit."""
        items = value if isinstance(value, tuple) and not self.enum else (value,)
        try:
            return all(self._admits_one(item) for item in items)
        except TypeError:  # a value of another type than the key's (Python callers; the loader checks types first)
            return False

    def _admits_one(self, value: Any) -> bool:
        if self.enum:
            return value in self.enum
        bounds = (
            self.minimum is None or value >= self.minimum,
            self.maximum is None or value <= self.maximum,
            self.exclusive_minimum is None or value > self.exclusive_minimum,
            self.exclusive_maximum is None or value < self.exclusive_maximum,
            self.multiple_of is None or value % self.multiple_of == 0,
        )
        return all(bounds)

    def describe(self) -> str:
        """What is accepted, for a refusal: `expected`, else the bounds or the choices in words."""
        if self.expected:
            return self.expected
        if self.enum:
            return one_of(str(choice) for choice in self.enum)
        words = [
            f"{word} {bound:g}"
            for word, bound in (
                ("≥", self.minimum),
                ("≤", self.maximum),
                (">", self.exclusive_minimum),
                ("<", self.exclusive_maximum),
                ("a multiple of", self.multiple_of),
            )
            if bound is not None
        ]
        return ", ".join(words)

    def as_schema(self) -> dict[str, Any]:
        """The JSON Schema keywords of this limit (`minimum`, `exclusiveMaximum`, `enum` …)."""
        keywords = {
            "minimum": self.minimum,
            "maximum": self.maximum,
            "exclusiveMinimum": self.exclusive_minimum,
            "exclusiveMaximum": self.exclusive_maximum,
            "multipleOf": self.multiple_of,
            "enum": list(self.enum) or None,
        }
        return {name: value for name, value in keywords.items() if value is not None}


@dataclass(frozen=True)
class Settings:
    """Base of the settings dataclasses: construction refuses a value outside its key's `Limit` or failing one of
    `checks()` (`check_settings`), naming `section.key`, the value and what is accepted.

    A subclass sets `section` (its TOML section, the prefix of its keys in messages), may set `error` (the
    exception type its callers catch), declares each key's plain range once in `limits` (a subclass of a
    subclass: `{**Base.limits, ...}`), and returns from `checks()` only the rules a `Limit` cannot state: a
    range that depends on another key, a rule computed by a function (`{**super().checks(), ...}` in a subclass
    of a subclass). Where a key has both, the `checks()` rule is the one applied.
    """

    section: ClassVar[str] = ""
    error: ClassVar[type[ValueError]] = SettingsError
    limits: ClassVar[Mapping[str, Limit]] = {}

    def __post_init__(self) -> None:
        plain = {key: (limit.admits(getattr(self, key)), limit.describe()) for key, limit in self.limits.items()}
        check_settings(self.section, self, {**plain, **self.checks()}, self.error)

    def checks(self) -> Checks:
        """Field name → (passed, what is expected) for the rules `limits` cannot state; none here."""
        return {}


class RangeError(ValueError):
    """A physical setting outside its accepted range; the message names it, its value and the range."""


@dataclass(frozen=True)
class PhysicalRange:
    """Closed interval [low, high] of a physical quantity in `unit`, with what it is (for messages)."""

    low: float
    high: float
    unit: str
    what: str

    def describe(self) -> str:
        """E.g. 'a baseline in metres from 0.001 to 10 m'."""
        return f"{self.what} from {self.low:g} to {self.high:g} {self.unit}"


#: The accepted ranges: 1 mm – 10 m baselines (a phone to a wide survey rig), 1 – 100,000 px
#: focal lengths, image sides up to `camera.MAX_IMAGE_SIDE_PX`, distances up to 655 m (what
#: MAVLink's DISTANCE_SENSOR can carry in uint16 centimetres) and cut offsets up to 2 m.
PHYSICAL_RANGES: dict[str, PhysicalRange] = {
    "baseline_m": PhysicalRange(0.001, 10.0, "m", "a baseline in metres"),
    "focal_px": PhysicalRange(1.0, 100_000.0, "px", "a focal length in pixels"),
    "image_side_px": PhysicalRange(1, MAX_IMAGE_SIDE_PX, "px", "an image width or height in pixels"),
    "distance_m": PhysicalRange(0.0, 655.0, "m", "a distance in metres"),
    "cut_offset_m": PhysicalRange(0.0, 2.0, "m", "an offset along the branch in metres"),
}


def in_physical_range(quantity: str, value: Any) -> tuple[bool, str]:
    """(whether `value` is a finite number within `PHYSICAL_RANGES[quantity]`, the range described):
    one entry of a `Settings.checks()` table."""
    accepted = PHYSICAL_RANGES[quantity]
    ok = (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and accepted.low <= value <= accepted.high
    )
    return ok, accepted.describe()


def check_physical(quantity: str, value: Any, name: str | None = None, error: type[ValueError] = RangeError) -> float:
    """`value` as a float when it is a finite number within `PHYSICAL_RANGES[quantity]`.

    Otherwise raises `error` naming `name` (the key, option or field the user wrote; default the
    quantity), the value and the accepted range: `--baseline-m = 1e+300: expected a baseline in
    metres from 0.001 to 10 m`.
    """
    accepted = PHYSICAL_RANGES[quantity]
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if not (math.isfinite(number) and accepted.low <= number <= accepted.high):
        raise error(f"{name or quantity} = {value!r}: expected {accepted.describe()}")
    return number


def check_image_size(
    width: Any, height: Any, name: str = "image size", error: type[ValueError] = RangeError
) -> tuple[int, int]:
    """(width, height) in pixels, each within the image-side range; else `error` naming `name`."""
    accepted = PHYSICAL_RANGES["image_side_px"]
    try:
        return tuple(int(check_physical("image_side_px", value, name, error)) for value in (width, height))  # type: ignore[return-value]
    except ValueError:
        raise error(
            f"{name} = {width}×{height}: expected each side from {accepted.low:g} to {accepted.high:g} {accepted.unit}"
        ) from None


def check_calibration(calibration: Any, size: tuple[int, int], name: str) -> None:
    """Refuse a calibration (`camera.StereoCalibration`) made for another image size than `size`
    (w, h) px, or whose focal lengths, baseline or image size are outside `PHYSICAL_RANGES`.

    Called where a calibration enters (an upload, `estimate --calib`), before a `Rectifier` sizes
    its maps by it; `name` (the file as the user knows it) leads the message.
    """
    require_image_size(calibration, size)
    for key in ("K1", "K2"):
        matrix = getattr(calibration, key)
        check_physical("focal_px", matrix[0, 0], f"{name}: {key} fx")
        check_physical("focal_px", matrix[1, 1], f"{name}: {key} fy")
    check_physical("baseline_m", calibration.baseline_m, f"{name}: baseline |T|")
