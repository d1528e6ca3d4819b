"""The TOML configuration: defaults, the deploy/ examples, and errors that name the key."""

from __future__ import annotations

import configparser
import re
import tomllib
from pathlib import Path

import pytest

from branchrange.config.loader import Config, config_from_dict, load_config
from branchrange.core.settings_check import ConfigError

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


def test_no_file_and_an_empty_file_give_the_defaults(tmp_path):
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    assert load_config(None) == load_config(empty) == Config()
    assert Config().mavlink.component_id == 191 and Config().api.host == "127.0.0.1"


def test_values_are_read_and_ints_are_accepted_for_floats(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(
        '[mavlink]\nurl = "/dev/ttyTHS1"\nbaud = 921600\nmax_result_age_s = 1\n'
        "[camera]\nmount_rpy_deg = [0, -20, 0]\nmount_xyz_m = [0.12, 0.0, 0.05]\n"
    )
    cfg = load_config(path)
    assert cfg.mavlink.url == "/dev/ttyTHS1" and cfg.mavlink.max_result_age_s == 1.0
    assert isinstance(cfg.mavlink.max_result_age_s, float)
    assert cfg.camera.mount_rpy_deg == (0.0, -20.0, 0.0) and cfg.camera.mount_xyz_m == (0.12, 0.0, 0.05)


@pytest.mark.parametrize(
    "data, message",
    [
        ({"mavlink": {"send_rate_hz": 1.0}}, r"mavlink\.send_rate_hz = 1\.0: expected at least 2 Hz"),
        ({"mavlink": {"system_id": 0}}, r"mavlink\.system_id = 0"),
        ({"mavlink": {"baud": "fast"}}, r"mavlink\.baud = 'fast': expected an integer"),
        ({"mavlink": {"target_as_obstacle": 1}}, r"mavlink\.target_as_obstacle = 1: expected true or false"),
        ({"camera": {"mount_rpy_deg": [0, 0]}}, r"camera\.mount_rpy_deg = \[0, 0\]: expected a list of 3 numbers"),
        ({"camera": {"mount_xyz_m": [0, "x", 0]}}, r"camera\.mount_xyz_m\[1\] = 'x'"),
        ({"stereo": {"backend": "raft"}}, r"stereo\.backend = 'raft': expected 'sgbm', 'emcstereo' or 'onnx'"),
        ({"stereo": {"max_disp": 190}}, r"stereo\.max_disp = 190: expected a positive multiple of 16"),
        (
            {"stereo": {"max_disp": 100, "backend": "emcstereo", "weights": "w.pth"}},
            r"stereo\.max_disp = 100: expected a positive multiple of 16",
        ),
        (
            {"stereo": {"backend": "emcstereo"}},
            r"stereo\.weights = '': expected a checkpoint path when stereo\.backend = 'emcstereo'",
        ),
        ({"camera": {"resolution": "HD720"}}, r"camera\.resolution: unknown option; \[camera\] takes calibration, "),
        ({"api": {"port": 70000}}, r"api\.port = 70000"),
        ({"api": {"prot": 8080}}, r"api\.prot: unknown option; \[api\] takes .*port"),
        ({"mavlnk": {}}, r"\[mavlnk\]: unknown section"),
        ({"log": {"level": "LOUD"}}, r"log\.level = 'LOUD'"),
        (
            {"mavlink": {"min_distance_m": 12.0}},
            r"mavlink\.min_distance_m = 12\.0: expected .*below mavlink\.max_distance_m",
        ),
        ({"mavlink": "udp"}, r"mavlink = 'udp': expected a table \[mavlink\]"),
    ],
)
def test_bad_values_name_the_key_and_what_was_expected(data, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict(data)


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match="nope.toml: configuration file not found"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[mavlink\nurl = 1")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load_config(bad)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[api]\nmax_concurrency = 0\n")
    with pytest.raises(ConfigError, match=r"wrong.toml: api\.max_concurrency = 0"):
        load_config(wrong)


def test_deploy_examples_load_with_the_values_they_document():
    onboard = load_config(DEPLOY / "onboard.toml")
    assert onboard.camera.source == "zed:/dev/zedmini:HD720"  # the udev rule's name for the ZED Mini
    assert (onboard.mavlink.url, onboard.mavlink.baud) == ("/dev/ttyTHS1", 921600)
    assert onboard.stereo.backend == "emcstereo" and onboard.stereo.weights.endswith(".pth")
    assert onboard.mavlink.target_as_obstacle is False and onboard.api.enabled is True
    assert onboard.stereo.mode == "roi" and onboard.stereo.max_disp == 128
    cpu = load_config(DEPLOY / "onboard_cpu.toml")  # a companion computer without a GPU
    assert (cpu.stereo.backend, cpu.stereo.mode, cpu.stereo.device, cpu.roi.coarse_width) == ("sgbm", "roi", "cpu", 640)
    assert cpu.camera == onboard.camera and cpu.log == onboard.log
    assert cpu.segmenter.learned.precision == "int8" and onboard.segmenter.learned.precision == "fp32"
    serve = load_config(DEPLOY / "serve.toml")
    assert serve.api.host == "0.0.0.0" and serve.mavlink.enabled is False and serve.api.retry_after_s == 2
    assert serve.stereo.mode == "full"  # accuracy over latency off the vehicle


@pytest.mark.parametrize("name", ["onboard.toml", "onboard_cpu.toml", "serve.toml"])
def test_each_deploy_file_acts_on_the_target_threshold_its_segmenter_was_calibrated_to(name):
    """A file that changes how the learned segmenter looks (precision, network width, trunk band) changes what a
    reported confidence means: its target threshold is the one the model's table gives for that setting."""
    import json

    from branchrange.core.segmentation.learned import SCENE_WIDTH, SHIPPED_MODELS

    cfg = load_config(DEPLOY / name)
    learned = cfg.segmenter.learned
    tables = json.loads(SHIPPED_MODELS[learned.precision].with_suffix(".json").read_text())["confidence_calibrations"]
    setting = (learned.network_width or SCENE_WIDTH, learned.trunk_band_px)
    table = next(t for t in tables if (t["network_width"], t["trunk_band_px"]) == setting)
    assert cfg.cutpoints.target_min_confidence == table["target_min_confidence"]


def test_deploy_files_agree_on_paths_names_and_devices():
    """The systemd unit, the container recipe, the udev rules and onboard.toml name the same things."""
    unit = configparser.ConfigParser(interpolation=None, strict=False)
    unit.optionxform = str  # systemd keys are case-sensitive
    unit.read(DEPLOY / "branchrange-daemon.service")
    service = unit["Service"]
    venv_bin, script, command, _, config_path = re.fullmatch(
        r"(/\S+/\.venv/bin)/(\S+) (\S+) (--config) (\S+)", service["ExecStart"]
    ).groups()
    scripts = tomllib.loads((DEPLOY.parent / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts[script] == "branchrange.cli:main" and command == "daemon"
    assert config_path == "/etc/branchrange/onboard.toml"
    onboard = load_config(DEPLOY / "onboard.toml")
    state_dir = f"/var/lib/{service['StateDirectory']}"
    assert onboard.log.results_jsonl.startswith(state_dir + "/") and service["ReadWritePaths"] == state_dir
    assert "2" in service["RestartPreventExitStatus"].split()  # exit status of a configuration error
    assert {"video", "dialout"} <= set(service["SupplementaryGroups"].split())
    # the ZED Mini is found by the udev rule's name, in the unit and in the container alike
    symlink = re.search(
        r'SUBSYSTEM=="video4linux".*SYMLINK\+="(\w+)"', (DEPLOY / "99-branchrange-cameras.rules").read_text()
    )
    assert onboard.camera.source.startswith(f"zed:/dev/{symlink.group(1)}:")
    docker = (DEPLOY / "Dockerfile.jetson").read_text()
    assert f"--device /dev/{symlink.group(1)}:/dev/{symlink.group(1)}" in docker
    assert f"--device {onboard.mavlink.url}" in docker  # the autopilot's serial port
    assert f'CMD ["{command}", "--config", "{config_path}"]' in docker and 'ENTRYPOINT ["branchrange"]' in docker
    assert f"WORKDIR {venv_bin.removesuffix('/.venv/bin')}" in docker
    # the container installs torch first and everything else with the tested pins
    pins = dict(
        line.split("==")
        for line in (DEPLOY / "constraints.txt").read_text().splitlines()
        if "==" in line and not line.startswith("#")
    )
    assert f'TORCH_SPEC="torch=={pins["torch"].split("+")[0]}"' in docker
    assert 'pip install -c /tmp/constraints-jetson.txt ".[ros]"' in docker  # rosbag: and --foxglove on the drone too
