"""The configuration's JSON Schema and Markdown reference, generated from the settings dataclasses: the shipped
copies equal the generated ones, every deploy/ file validates, a mistyped key is refused, every declared
`Limit` says what the class's `checks()` accepts, and each key's description comes from its class."""

from __future__ import annotations

import dataclasses
import tomllib
import typing
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from branchrange.config.descriptions import key_description
from branchrange.config.loader import Config
from branchrange.config.reference import config_reference, range_text, type_text
from branchrange.config.schema import SCHEMA_PATH, config_schema, schema_text, unit_of
from branchrange.config.sections import ApiConfig
from branchrange.core.pipeline import StereoConfig
from branchrange.core.segmentation.onnx_model import OnnxSegmenterConfig
from branchrange.core.settings_check import Limit
from branchrange.core.tracking import TrackerConfig

ROOT = Path(__file__).resolve().parents[1]
DEPLOY_FILES = sorted((ROOT / "deploy").glob("*.toml"))


def settings_classes(cls: type = Config) -> list[type]:
    """Every settings dataclass below `Config`: the sections and their sub-tables."""
    found = []
    for field in dataclasses.fields(cls):
        kind = typing.get_type_hints(cls)[field.name]
        if dataclasses.is_dataclass(kind):
            found += [kind, *settings_classes(kind)]
    return found


@pytest.fixture(scope="module")
def schema() -> dict[str, Any]:
    return config_schema()


@pytest.fixture(scope="module")
def validator(schema) -> jsonschema.Draft202012Validator:
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_the_shipped_schema_is_the_generated_one(schema):
    """Regenerate with `branchrange config schema > branchrange/config/config.schema.json`."""
    assert SCHEMA_PATH.read_text(encoding="utf-8") == schema_text(schema)


def test_the_committed_reference_is_the_generated_one(schema):
    """Regenerate with `branchrange config reference > docs/configuration.md`."""
    assert (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8") == config_reference(schema)


@pytest.mark.parametrize("path", DEPLOY_FILES, ids=lambda p: p.name)
def test_every_deploy_file_names_the_shipped_schema_and_validates_against_it(path, validator):
    first_line = path.read_text(encoding="utf-8").splitlines()[0]
    assert first_line.startswith("#:schema ")
    # Taplo / Even Better TOML resolve a relative #:schema path from the TOML file's folder
    assert (path.parent / first_line.removeprefix("#:schema ")).resolve() == SCHEMA_PATH
    errors = list(validator.iter_errors(tomllib.loads(path.read_text(encoding="utf-8"))))
    assert errors == []


@pytest.mark.parametrize(
    "data, path",
    [
        ({"cutpoints": {"target_min_confidnce": 0.7}}, ["cutpoints"]),  # a mistyped key
        ({"mavlnk": {"url": "/dev/ttyTHS1"}}, []),  # a mistyped section
        ({"segmenter": {"structure": {"plane_share": 0.1}}}, ["segmenter", "structure"]),  # in a sub-table
    ],
)
def test_the_schema_refuses_a_mistyped_key(validator, data, path):
    (error,) = validator.iter_errors(data)
    assert error.validator == "additionalProperties" and list(error.absolute_path) == path


@pytest.mark.parametrize(
    "data",
    [
        {"stereo": {"backend": "raft"}},
        {"stereo": {"max_disp": 100}},
        {"api": {"port": 70000}},
        {"mavlink": {"baud": "fast"}},
        {"camera": {"mount_xyz_m": [0, 0]}},
        {"masks": {"ignored_ids": [0]}},
        {"log": {"level": "LOUD"}},
        {"segmenter": {"learned": {"precision": "fp8"}}},
    ],
)
def test_the_schema_refuses_a_wrong_type_or_a_value_out_of_range(validator, data):
    assert len(list(validator.iter_errors(data))) == 1


def test_every_key_of_the_configuration_is_in_the_schema_with_its_default(schema):
    def walk(settings: object, table: dict[str, Any], prefix: str) -> list[str]:
        keys = []
        assert set(table["properties"]) == {f.name for f in dataclasses.fields(settings)}, prefix
        for field in dataclasses.fields(settings):
            value, sub = getattr(settings, field.name), table["properties"][field.name]
            if dataclasses.is_dataclass(value):
                keys += walk(value, sub, f"{prefix}{field.name}.")
            else:
                assert sub["default"] == (list(value) if isinstance(value, tuple) else value), prefix + field.name
                keys.append(prefix + field.name)
        return keys

    defaults = Config()
    keys = [
        key
        for name in schema["properties"]
        for key in walk(getattr(defaults, name), schema["properties"][name], f"{name}.")
    ]
    assert len(keys) > 130 and "segmenter.learned.network_width" in keys


# --- every Limit agrees with checks() -------------------------------------------------------------------

#: Values a class needs besides the one probed, so only the probed key can be refused.
PROBE_CONTEXT: dict[type, dict[str, Any]] = {
    StereoConfig: {"weights": "w.pth"},  # a network backend needs weights
    OnnxSegmenterConfig: {"branch_classes": (5,)},  # a class id cannot be both branch and trunk
}
#: Bounds no value reaches alone because another key must lie beyond them: the lower end of a working range
#: can be at most its upper end's maximum, and the upper end at least the lower end's minimum, only not equal.
REACHED_ONLY_WITH_ANOTHER_KEY = {
    ("min_range_m", "maximum"),
    ("max_range_m", "minimum"),
    ("min_distance_m", "maximum"),
    ("max_distance_m", "minimum"),
}


def accepted(cls: type, key: str, value: Any) -> bool:
    """Whether settings class `cls` accepts `value` for `key` (a list field gets it as its one item)."""
    kind = typing.get_type_hints(cls)[key]
    if typing.get_origin(kind) is tuple:
        value = (value,)
    context = next((c for base, c in PROBE_CONTEXT.items() if issubclass(cls, base)), {})
    try:
        cls(**{**context, key: value})
    except (ValueError, TypeError):  # TypeError: a value of another type than the field's
        return False
    return True


def limit_probes() -> list[tuple[type, str, Any]]:
    return [(cls, key, limit) for cls in dict.fromkeys(settings_classes()) for key, limit in cls.limits.items()]


def disagreements(cls: type, key: str, limit: Limit) -> list[str]:
    """Where `limit` and the checks of `cls` disagree on `key`: a bound whose far side passes, a bound or an enum
    value refused, an exclusive bound accepted, a value off the multiple accepted."""
    kind = typing.get_type_hints(cls)[key]
    number = (typing.get_args(kind)[0] if typing.get_origin(kind) is tuple else kind) is int
    step = 1 if number else 1e-6
    found = [f"{choice!r} refused" for choice in limit.enum if not accepted(cls, key, choice)]
    if limit.enum and accepted(cls, key, "not-a-choice"):
        found.append("a value outside the enum accepted")
    bounds = [
        ("minimum", limit.minimum, -step, True),
        ("maximum", limit.maximum, +step, True),
        ("exclusive minimum", limit.exclusive_minimum, -step, False),
        ("exclusive maximum", limit.exclusive_maximum, +step, False),
    ]
    for side, bound, outward, inclusive in bounds:
        if bound is None:
            continue
        bound = int(bound) if number else float(bound)
        if accepted(cls, key, bound + outward):
            found.append(f"{side} {bound}: {bound + outward} accepted")
        if (key, side) in REACHED_ONLY_WITH_ANOTHER_KEY:
            continue
        if accepted(cls, key, bound) != inclusive:
            found.append(f"{side} {bound}: the bound itself {'refused' if inclusive else 'accepted'}")
        if not inclusive and not accepted(cls, key, bound - outward):
            found.append(f"{side} {bound}: {bound - outward} refused")
    if limit.multiple_of and accepted(cls, key, int(limit.minimum or 0) + limit.multiple_of // 2):
        found.append(f"a value off the multiple of {limit.multiple_of} accepted")
    return found


@pytest.mark.parametrize("cls, key, limit", limit_probes(), ids=[f"{c.section}.{k}" for c, k, _ in limit_probes()])
def test_each_declared_limit_says_what_checks_accept(cls, key, limit):
    assert disagreements(cls, key, limit) == []


@pytest.mark.parametrize(
    "limit, disagreement",
    [
        (Limit(minimum=0, maximum=70000), "maximum 70000: the bound itself refused"),  # wider than the checks
        (Limit(minimum=0, maximum=1024), "maximum 1024: 1025 accepted"),  # narrower: 1025 passes the checks
        (Limit(exclusive_minimum=0, maximum=65535), "exclusive minimum 0: the bound itself accepted"),
        (Limit(enum=("8080",)), "'8080' refused"),
    ],
)
def test_a_limit_that_disagrees_with_the_checks_is_found(limit, disagreement):
    assert disagreement in disagreements(ApiConfig, "port", limit)


# --- descriptions, units and the reference's words -----------------------------------------------------


def test_descriptions_come_from_bullets_inline_definitions_and_sentences(schema):
    cutpoints = schema["properties"]["cutpoints"]["properties"]
    assert cutpoints["cut_offset_m"]["description"] == (
        "[m] distance of the cut from the base along the axis (just outside the collar)."
    )
    # a bullet shared by two keys
    assert key_description(Config().cutpoints.__class__, "cut_disparity_noise_px").startswith(
        "the confidence includes the chance"
    )
    # inline definitions in prose, separated by semicolons
    assert key_description(TrackerConfig, "max_missed") == "frames a track survives unseen"
    # a sentence that names the key
    assert schema["properties"]["camera"]["properties"]["source"]["description"].startswith(
        "`source` is a `camera.sources.open_source` spec"
    )
    # a key documented by a base class (OnnxSegmenterConfig's bullets for [segmenter])
    assert schema["properties"]["segmenter"]["properties"]["nms_iou"]["description"].startswith("IoU above which")


@pytest.mark.parametrize(
    "key, unit",
    [
        ("setpoint_max_speed_m_s", "m/s"),
        ("process_noise_m2_per_s", "m²/s"),
        ("gate_m", "m"),
        ("stall_timeout_s", "s"),
        ("mount_rpy_deg", "degrees"),
        ("box_margin_px", "px"),
        ("send_rate_hz", "Hz"),
        ("max_upload_mb", "MiB"),
        ("max_disp", ""),
        ("results_jsonl", ""),
    ],
)
def test_units_come_from_the_key_name(key, unit):
    assert unit_of(key) == unit


@pytest.mark.parametrize(
    "schema, words",
    [
        ({"minimum": 0, "maximum": 1}, "[0, 1]"),
        ({"exclusiveMinimum": 0, "maximum": 5}, "(0, 5]"),
        ({"minimum": 0, "exclusiveMaximum": 10}, "[0, 10)"),
        ({"exclusiveMinimum": 0}, "> 0"),
        ({"minimum": 3}, "≥ 3"),
        ({"minimum": 16, "maximum": 512, "multipleOf": 16}, "[16, 512], multiple of 16"),
        ({"enum": ["full", "roi"]}, 'one of "full", "roi"'),
        ({"items": {"minimum": 1, "maximum": 65535}}, "each [1, 65535]"),
        ({}, ""),
    ],
)
def test_the_reference_states_ranges_in_words(schema, words):
    assert range_text(schema) == words


def test_the_reference_states_types_in_words(schema):
    camera = schema["properties"]["camera"]["properties"]
    masks = schema["properties"]["masks"]["properties"]
    assert (type_text(camera["mount_xyz_m"]), type_text(masks["ignored_ids"]), type_text(camera["source"])) == (
        "3 × number",
        "list of integer",
        "string",
    )


def test_the_reference_has_a_row_for_every_key_and_a_heading_for_every_table(schema):
    text = config_reference(schema)
    assert "## [segmenter.structure]" in text and "## [branch_tracking]" in text
    row = next(line for line in text.splitlines() if line.startswith("| `max_disp` |"))
    assert row.split(" | ")[1:5] == ["integer", "", "`192`", "[16, 512], multiple of 16"]


def test_every_key_is_described_by_its_settings_class():
    """A new key without a bullet (or a sentence naming it) in its class docstring would reach the editor and the
    reference without a word about what it does."""
    undocumented = []
    for cls in dict.fromkeys(settings_classes()):
        hints = typing.get_type_hints(cls)
        for field in dataclasses.fields(cls):
            if not dataclasses.is_dataclass(hints[field.name]) and not key_description(cls, field.name):
                undocumented.append(f"{cls.section}.{field.name}")
    assert undocumented == []
