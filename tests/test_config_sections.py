"""Each TOML section is the dataclass its code uses: every option settable from the file and from
`--set`, errors naming the key however the value came in, one list of backends and precisions,
one max_disp rule, and every example in deploy/ loading."""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path
from typing import Any

import pytest

from branchrange.cli import main
from branchrange.config.loader import Config, config_from_dict, load_config, parse_override, pipeline_config
from branchrange.core.pipeline import Pipeline, StereoConfig
from branchrange.core.settings_check import ConfigError
from stereo.backends import BACKEND_NAMES, PRECISIONS, BackendConfigError, SGBMBackend

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
#: Non-default values for the string options, and for numbers whose neighbours of the default are all refused
#: (each must pass its section's checks).
STRINGS = {
    "camera.source": "oak",
    "camera.calibration": "cal.conf",
    "stereo.backend": "emcstereo",
    "stereo.weights": "other.pth",
    "stereo.device": "cuda",
    "stereo.precision": "bf16",
    "stereo.mode": "full",
    "cutpoints.target_policy": "thickest",
    "masks.kind": "binary",
    "segmenter.model": "geometric",
    "segmenter.learned.model": "my_branchnet.onnx",
    "segmenter.learned.precision": "int8",
    "segmenter.learned.device": "tensorrt",  # accepted by the settings; its provider is checked when it is built
    "segmenter.learned.network_width": 1280,  # 0 (the frame's own) or 160..4096
    "segmenter.input_size": 320,  # 0 (the model's export size) or stride..8192
    "mavlink.url": "tcp:127.0.0.1:5760",
    "mavlink.signing_key_file": "k.key",
    "api.host": "0.0.0.0",
    "api.token": "s3cret",
    "log.results_jsonl": "r.jsonl",
    "log.level": "DEBUG",
}
#: Every config needs weights once the backend is a network: the base every single change is made on.
BASE = {"stereo": {"weights": "w.pth"}}


def leaves(cls: type, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted key, type, default) of every option below settings class `cls`, sub-tables included."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if dataclasses.is_dataclass(hints[f.name]):
            out += [(f"{key}.{k}", t, d) for k, t, d in leaves(hints[f.name], "")]
        else:
            out.append((key, hints[f.name], default))
    return out


def option_keys() -> list[tuple[str, Any, Any]]:
    """Every option of the file, with its type and its default in `Config()`."""
    defaults = Config()
    keys = []
    for section in dataclasses.fields(Config):
        for key, kind, _ in leaves(typing.get_type_hints(Config)[section.name]):
            value: Any = getattr(defaults, section.name)
            for part in key.split("."):
                value = getattr(value, part)
            keys.append((f"{section.name}.{key}", kind, value))
    return keys


def other_value(key: str, kind: Any, default: Any) -> Any:
    """A TOML value for `key` that differs from `default` and is accepted."""
    if key in STRINGS:
        return STRINGS[key]
    if kind is bool:
        return not default
    if kind in (int, float):
        for candidate in (default + 1, default * 2, default - 1, default / 2, 1, 0):
            candidate = kind(candidate)
            try:
                config_from_dict(tree_with(key, candidate))
            except ConfigError:
                continue
            if candidate != default:
                return candidate
    if typing.get_origin(kind) is tuple:
        if typing.get_args(kind)[1:] == (Ellipsis,):
            return [3, 4] if default != (3, 4) else [5]
        return [1.5, -2.0, 3.0]
    raise AssertionError(f"no other value for {key} ({kind}, default {default!r})")


def tree_with(key: str, value: Any) -> dict:
    """The parsed-TOML tree of `BASE` with `key` set to `value`."""
    tree = json.loads(json.dumps(BASE))
    *tables, last = key.split(".")
    node = tree
    for name in tables:
        node = node.setdefault(name, {})
    node[last] = value
    return tree


def toml_literal(value: Any) -> str:
    """`value` as TOML source (what a user types after `--set KEY=`)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_literal(v) for v in value) + "]"
    return json.dumps(value) if isinstance(value, str) else repr(value)


def toml_document(tree: dict, prefix: str = "") -> str:
    """The TOML file of a parsed tree: each table's keys, then its sub-tables."""
    text = "".join(f"{k} = {toml_literal(v)}\n" for k, v in tree.items() if not isinstance(v, dict))
    for name, table in ((k, v) for k, v in tree.items() if isinstance(v, dict)):
        text += f"[{prefix}{name}]\n" + toml_document(table, f"{prefix}{name}.")
    return text


def read_back(cfg: Config, key: str) -> Any:
    value: Any = cfg
    for part in key.split("."):
        value = getattr(value, part)
    return list(value) if isinstance(value, tuple) else value


OPTIONS = option_keys()


def test_the_file_has_every_option_of_the_pipeline_sections():
    keys = {key for key, _, _ in OPTIONS}
    assert len([k for k in keys if k.startswith("cutpoints.")]) == 18  # all of CutPointConfig
    assert {
        "segmenter.structure.plane_min_share",
        "segmenter.geometric.excess_green",
        "segmenter.nms_iou",
        "branch_tracking.max_missed",
        "masks.trunk_id",
        "stereo.precision",
        "roi.network_regions",
    } <= keys


@pytest.mark.parametrize("key, kind, default", OPTIONS, ids=[key for key, _, _ in OPTIONS])
def test_every_option_is_settable_in_the_file_and_with_set(key, kind, default, tmp_path):
    value = other_value(key, kind, default)
    assert value != (list(default) if isinstance(default, tuple) else default)
    path = tmp_path / "c.toml"
    path.write_text(toml_document(tree_with(key, value)))
    assert read_back(load_config(path), key) == value
    from_set = load_config(
        None, [parse_override('stereo.weights="w.pth"'), parse_override(f"{key}={toml_literal(value)}")]
    )
    assert read_back(from_set, key) == value


def test_set_wins_over_the_file_and_a_bare_word_is_a_string(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[stereo]\nmax_disp = 64\nbackend = "sgbm"\n')
    cfg = load_config(path, [parse_override("stereo.max_disp=128"), parse_override("stereo.mode=full")])
    assert (cfg.stereo.max_disp, cfg.stereo.mode, cfg.stereo.backend) == (128, "full", "sgbm")
    assert load_config(path).stereo.max_disp == 64


@pytest.mark.parametrize(
    "text, message",
    [
        ("stereo", r"--set 'stereo': expected SECTION\.KEY=VALUE"),
        ("max_disp=64", r"--set 'max_disp=64': expected SECTION\.KEY=VALUE"),
        ("stereo.max_disp=abc", r"stereo\.max_disp = 'abc': expected an integer"),
        ("stereo.max_disp=100", r"stereo\.max_disp = 100: expected a positive multiple of 16 up to 512 px"),
        ("cutpoints.cut_ofset_m=0.1", r"cutpoints\.cut_ofset_m: unknown option; \[cutpoints\] takes .*cut_offset_m"),
        ("cutpoints.min_points=2", r"cutpoints\.min_points = 2: expected ≥ 3 points"),
        (
            "cutpoints.max_range_m=900",
            r"cutpoints\.max_range_m = 900\.0: expected .*a distance in metres from 0 to 655 m",
        ),
        ("segmenter.structure.max_range_m=0.1", r"segmenter\.structure\.max_range_m = 0\.1: expected > min_range_m"),
        (
            "segmenter.structure.plane_share=0.1",
            r"segmenter\.structure\.plane_share: unknown option; \[segmenter\.structure\]",
        ),
        ("segmenter.structure=3", r"segmenter\.structure = 3: expected a table \[segmenter\.structure\]"),
        ("stereo.backend.name=x", r"stereo\.backend = \{'name': 'x'\}: expected a string"),
        ("branch_tracking.max_axis_angle_deg=200", r"branch_tracking\.max_axis_angle_deg = 200\.0: expected an angle"),
        ("masks.kind=rgb", r"masks\.kind = 'rgb': expected 'auto', 'instance' or 'binary'"),
        ("stereo.precision=int8", r"stereo\.precision = 'int8': expected 'fp32', 'fp16' or 'bf16'"),
        (
            "segmenter.model=maskrcnn",
            r"segmenter\.model = 'maskrcnn': expected 'learned', 'geometric', 'structure' or 'onnx:FILE'",
        ),
    ],
)
def test_set_errors_name_the_key_and_what_was_expected(text, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [parse_override(text)])


def test_file_errors_name_the_file_and_set_errors_do_not(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[masks]\ntrunk_id = 0\n")
    with pytest.raises(ConfigError, match=r"c\.toml: masks\.trunk_id = 0: expected an id in 1\.\.65535"):
        load_config(path)
    path.write_text("[masks]\ntrunk_id = 7\n")
    with pytest.raises(ConfigError, match=r"^masks\.trunk_id = 0"):
        load_config(path, [parse_override("masks.trunk_id=0")])
    with pytest.raises(ConfigError, match=r"^masks\.trunk_id = 7: expected a table \(--set masks\.trunk_id\.x=…\)"):
        load_config(path, [parse_override("masks.trunk_id.x=1")])


@pytest.mark.parametrize("path", sorted(DEPLOY.glob("*.toml")), ids=lambda p: p.name)
def test_every_deploy_example_loads_and_takes_set(path):
    cfg = load_config(path)
    assert pipeline_config(cfg).stereo is cfg.stereo  # the section object itself, not a copy
    changed = load_config(path, [parse_override("segmenter.structure.max_range_m=3.5")])
    assert changed.segmenter.structure.max_range_m == 3.5 and changed.stereo == cfg.stereo


def test_sections_reach_the_pipeline_stages_themselves():
    cfg = load_config(
        None,
        [
            parse_override("segmenter.learned.max_trunk_gap_m=0.2"),
            parse_override("branch_tracking.gate_m=0.2"),
            parse_override("cutpoints.erode_px=2"),
        ],
    )
    pipeline = Pipeline(pipeline_config(cfg), focal_px=500.0, baseline_m=0.063)
    assert pipeline.segmenter.config is cfg.segmenter.learned and pipeline.tracker.config.gate_m == 0.2
    assert pipeline.config.cutpoints is cfg.cutpoints
    assert cfg.segmenter.build("geometric").config is cfg.segmenter.geometric
    assert cfg.segmenter.build("structure").config is cfg.segmenter.structure


def test_one_list_of_backends_and_precisions():
    for backend in BACKEND_NAMES:
        assert StereoConfig(backend=backend, weights="w").backend == backend
    for precision in PRECISIONS:
        assert StereoConfig(precision=precision).precision == precision
    from api import create_app
    from branchrange.config.sections import ApiConfig

    class _Unused:  # the OpenAPI document is built without an estimator being called
        backend_name = "sgbm"

    schema = create_app(ApiConfig(), _Unused()).openapi()
    form = schema["components"]["schemas"]["Body_post_estimate_estimate_post"]["properties"]["backend"]
    assert [e for option in form["anyOf"] for e in option.get("enum", [])] == list(BACKEND_NAMES)


@pytest.mark.parametrize("max_disp", [100, 528, 0])
def test_one_max_disp_rule_for_config_backend_api_and_command_line(max_disp, capsys, tmp_path):
    with pytest.raises(ConfigError, match=rf"stereo\.max_disp = {max_disp}: expected a positive multiple of 16"):
        StereoConfig(max_disp=max_disp)
    with pytest.raises(BackendConfigError, match=rf"max_disp = {max_disp}: expected a positive multiple of 16"):
        SGBMBackend(max_disp)
    from fastapi.testclient import TestClient

    from api import create_app
    from api.estimator import PipelineEstimator
    from branchrange.config.sections import ApiConfig

    with TestClient(create_app(ApiConfig(), PipelineEstimator())) as client:
        r = client.post(
            "/estimate",
            files={"left": ("l.png", b"x", "image/png"), "right": ("r.png", b"x", "image/png")},
            data={"focal_px": "500", "baseline_m": "0.063", "max_disp": str(max_disp)},
        )
    assert r.status_code == 422 and f"max_disp = {max_disp}: expected a positive multiple of 16" in r.text
    assert (
        main(
            [
                "estimate",
                "--left",
                str(tmp_path / "l.png"),
                "--right",
                str(tmp_path / "r.png"),
                "--focal-px",
                "500",
                "--baseline-m",
                "0.063",
                "--max-disp",
                str(max_disp),
            ]
        )
        == 2
    )
    assert f"stereo.max_disp = {max_disp}" in capsys.readouterr().err


def test_commands_that_read_the_config_take_set_and_name_the_key(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text('[camera]\nsource = "replay:nowhere"\n')
    assert main(["daemon", "--config", str(path), "--set", "stereo.max_disp=100"]) == 2
    assert "--set: stereo.max_disp: 100 is not a multiple of 16" in capsys.readouterr().err  # as config check says
    assert main(["serve", "--set", "api.port=http"]) == 2
    assert "--set: api.port: 'http' is not of type 'integer'" in capsys.readouterr().err
    assert main(["replay", str(tmp_path), "--out", str(tmp_path / "r.jsonl"), "--set", "cutpoints.erode_px=-1"]) == 2
    assert "cutpoints.erode_px = -1: expected ≥ 0 px" in capsys.readouterr().err
    # a flag is the shorthand of one key; --set comes after it
    assert (
        main(
            [
                "replay",
                str(tmp_path),
                "--out",
                str(tmp_path / "r.jsonl"),
                "--max-disp",
                "64",
                "--set",
                "stereo.max_disp=90",
            ]
        )
        == 2
    )
    assert "stereo.max_disp = 90" in capsys.readouterr().err
