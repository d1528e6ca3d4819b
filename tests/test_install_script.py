"""deploy/install.sh: what `--dry-run` says it would do on each kind of machine, and the tree a real
`--prefix` run writes.

The machine is faked by `--detect-root DIR`, a folder holding the files the script looks at
(`etc/os-release`, `etc/nv_tegra_release` for JetPack, `proc/driver/nvidia/version` for an NVIDIA
driver). The real runs skip pip (`--skip-pip`): the venv is made beforehand, without pip, and
sees this checkout and the test interpreter's packages through a `.pth` file, so every
file-writing step and the `branchrange config` calls run for real in about ten seconds.
"""

from __future__ import annotations

import configparser
import os
import re
import stat
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from branchrange.config.loader import load_config

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "deploy" / "install.sh"
#: The step headings, in the order the script runs them.
STEPS = [
    "system packages",
    "service user branchrange",
    "folders",
    "venv",
    "torch",
    "branchrange with extras",
    "weights",
    "calibration",
    "configuration",
    "systemd unit and udev rules",
    "systemd and udev",
    "preflight",
]
HEADING = re.compile(r"^==> \[(\d+)/(\d+)\] (.*)$", re.MULTILINE)


def fake_machine(root: Path, *, jetpack: bool = False, nvidia_driver: bool = False) -> Path:
    """A folder standing for `/` of a Debian machine, a JetPack one, or one with an NVIDIA driver."""
    (root / "etc").mkdir(parents=True)
    system = 'ID=ubuntu\nVERSION_ID="22.04"\n' if jetpack else 'ID=debian\nVERSION_ID="12"\n'
    (root / "etc" / "os-release").write_text(system)
    if jetpack:
        (root / "etc" / "nv_tegra_release").write_text("# R36 (release), REVISION: 4.0\n")
    if nvidia_driver:
        (root / "proc" / "driver" / "nvidia").mkdir(parents=True)
        (root / "proc" / "driver" / "nvidia" / "version").write_text("NVRM version: NVIDIA UNIX x86_64 Kernel Module\n")
    return root


def install(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """Run the script with this interpreter as the venv's maker; its output, whatever its exit status."""
    command = ["bash", str(SCRIPT), "--python", sys.executable, *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def dry_run(tmp_path: Path, machine: Path, *args: str | Path) -> str:
    """The printed plan of a `--dry-run` into tmp_path/prefix, which must stay untouched."""
    prefix = tmp_path / "prefix"
    result = install("--dry-run", "--prefix", prefix, "--detect-root", machine, *args)
    assert result.returncode == 0, result.stderr
    assert not prefix.exists()  # a dry run changes nothing
    return result.stdout


def headings(output: str) -> list[str]:
    found = HEADING.findall(output)
    assert [int(number) for number, _, _ in found] == list(range(1, len(STEPS) + 1))
    assert {total for _, total, _ in found} == {str(len(STEPS))}
    return [title for _, _, title in found]


def commands(output: str) -> list[str]:
    return [line.strip().removeprefix("$ ") for line in output.splitlines() if line.strip().startswith("$ ")]


def test_dry_run_on_a_cpu_debian_machine_prints_every_step_in_order(tmp_path):
    output = dry_run(tmp_path, fake_machine(tmp_path / "machine"))
    titles = headings(output)
    assert [title for title, step in zip(titles, STEPS) if title.startswith(step)] == titles
    assert "torch cpu" in output and "config onboard_cpu.toml" in output
    run = commands(output)
    prefix = tmp_path / "prefix"
    venv_python = f"{prefix}/opt/branchrange/.venv/bin/python"
    torch_line = next(line for line in run if line.startswith(f"{venv_python} -m pip install") and "torch==" in line)
    assert "--index-url https://download.pytorch.org/whl/cpu" in torch_line and "torch==2.13.0" in torch_line
    project_line = next(line for line in run if line.endswith(f"'{ROOT}[ros,coco,onnx]'"))
    assert f"-c {ROOT}/deploy/constraints.txt" in project_line  # every version pinned as tested
    assert f"{sys.executable} -m venv {prefix}/opt/branchrange/.venv" in run
    check = f"{prefix}/opt/branchrange/.venv/bin/branchrange config check"
    assert f"{check} --file-only {prefix}/etc/branchrange/onboard.toml" in run  # the file: a problem stops it
    assert f"{check} --for daemon {prefix}/etc/branchrange/onboard.toml" in run  # the machine: listed
    # not root, not /: no user, no systemctl, and preflight comes last, as the service would run it
    assert not any(line.startswith(("useradd", "systemctl", "udevadm", "chown")) for line in run)
    preflight = (
        f"{prefix}/opt/branchrange/.venv/bin/branchrange preflight --config {prefix}/etc/branchrange/onboard.toml"
    )
    assert run[-1] == preflight
    assert "none needed: onboard_cpu.toml names no stereo weights" in output


def test_dry_run_with_an_nvidia_driver_takes_pypi_cuda_torch_and_the_cuda_configuration(tmp_path):
    output = dry_run(tmp_path, fake_machine(tmp_path / "machine", nvidia_driver=True), "--no-preflight")
    headings(output)
    assert "torch cuda" in output and "config onboard.toml" in output
    torch_line = next(line for line in commands(output) if "pip install" in line and "torch==" in line)
    assert "--index-url" not in torch_line  # PyPI's Linux x86-64 torch is the CUDA build
    assert any("torch.version.cuda is None" in line for line in commands(output))  # checked before going on
    assert "missing: " in output and "emcstereo_virtualtree_best.pth" in output  # EMCStereo needs its weights
    assert "skipped (--no-preflight)" in output


def test_dry_run_on_jetpack_takes_cpu_torch_with_the_cpu_configuration_and_the_jetson_uart(tmp_path):
    output = dry_run(tmp_path, fake_machine(tmp_path / "machine", jetpack=True))
    headings(output)
    assert "(JetPack)" in output and "torch cpu" in output and "config onboard_cpu.toml" in output
    assert 'set mavlink.url = "/dev/ttyTHS1"' in output  # not the Raspberry Pi's /dev/ttyAMA0


def test_dry_run_on_jetpack_with_a_cuda_wheel_takes_the_cuda_configuration(tmp_path):
    wheel = tmp_path / "torch-2.5.0a0-cp311-cp311-linux_aarch64.whl"
    output = dry_run(tmp_path, fake_machine(tmp_path / "machine", jetpack=True), "--torch-spec", wheel)
    headings(output)
    assert "torch cuda" in output and "config onboard.toml" in output
    torch_line = next(line for line in commands(output) if "pip install" in line and str(wheel) in line)
    assert "deploy/constraints.txt" not in torch_line  # every pin but torch's: the wheel's own version stays
    assert "set mavlink.url" not in output  # onboard.toml already names the Jetson's UART


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="the system install's plan needs root")
def test_dry_run_as_root_on_slash_plans_the_user_the_owners_systemd_and_preflight_as_the_service(tmp_path):
    result = install("--dry-run", "--detect-root", fake_machine(tmp_path / "machine"))
    assert result.returncode == 0, result.stderr
    headings(result.stdout)
    run = commands(result.stdout)
    assert "apt-get update" in run or "already installed" in result.stdout  # libusb, the venv module
    expected_in_order = [
        "chown root:branchrange /etc/branchrange",
        "chown branchrange:branchrange /var/lib/branchrange",
        "udevadm control --reload",
        "systemctl daemon-reload",
        "systemctl enable branchrange-daemon.service",
        "runuser -u branchrange -- /opt/branchrange/.venv/bin/branchrange preflight"
        " --config /etc/branchrange/onboard.toml",
        "systemctl restart branchrange-daemon.service",
    ]
    positions = [run.index(line) for line in expected_in_order]
    assert positions == sorted(positions)
    assert any(line.startswith(("useradd --system", "usermod --append")) for line in run)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--config", "onboard.toml"], "use --config onboard_cpu.toml"),  # the Jetson mismatch, refused up front
        (["--torch", "cuda"], "needs --torch-spec WHEEL"),
        (["--torch", "rocm"], "--torch rocm: expected auto, cpu or cuda"),
        (["--calibration", "/nonexistent/SN1.conf"], "--calibration /nonexistent/SN1.conf: no such file"),
        (["--set", "camera source=x"], "expected SECTION.KEY=VALUE"),
        (["--prefix"], "--prefix needs a value"),
        (["--frobnicate"], "unknown option --frobnicate"),
    ],
)
def test_bad_options_stop_before_any_step_with_exit_status_2(tmp_path, args, message):
    result = install("--dry-run", "--detect-root", fake_machine(tmp_path / "machine", jetpack=True), *args)
    assert result.returncode == 2 and message in result.stderr
    assert "==>" not in result.stdout and "Traceback" not in result.stderr


def test_a_refused_install_leaves_the_prefix_untouched(tmp_path):
    prefix = tmp_path / "prefix"
    result = install(
        "--prefix", prefix, "--detect-root", fake_machine(tmp_path / "machine"), "--config", "onboard.toml"
    )
    assert result.returncode == 2 and "the daemon would refuse to start" in result.stderr
    assert not prefix.exists()


def premade_venv(prefix: Path) -> Path:
    """The venv at the unit's path, made without pip: this checkout and the test's packages on its path,
    and `branchrange`/`emcstereo` commands as pip would have written them."""
    venv = prefix / "opt" / "branchrange" / ".venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=60)
    site_packages = next((venv / "lib").glob("python3*/site-packages"))
    (site_packages / "checkout.pth").write_text(f"{ROOT}\n{sysconfig.get_paths()['purelib']}\n")
    for command, module in (("branchrange", "branchrange.cli"), ("emcstereo", "stereo.cli")):
        script = venv / "bin" / command
        script.write_text(f'#!/bin/sh\nexec "$(dirname "$0")/python" -m {module} "$@"\n')
        script.chmod(0o755)
    return venv


def real_install(tmp_path: Path, *args: str | Path) -> subprocess.CompletedProcess[str]:
    machine = tmp_path / "machine"
    if not machine.exists():
        fake_machine(machine)
    return install(
        "--prefix", tmp_path / "prefix", "--detect-root", machine, "--skip-pip", "--no-systemd", "--no-preflight", *args
    )


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.skipif(os.name != "posix", reason="a bash script for Linux")
def test_a_prefix_install_writes_a_service_tree_whose_paths_point_into_the_prefix(tmp_path):
    prefix = tmp_path / "prefix"
    venv = premade_venv(prefix)
    result = real_install(tmp_path, "--set", 'mavlink.url="udpout:127.0.0.1:14550"')
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"kept: {venv} already holds a CPython 3.11 or newer" in result.stdout
    etc, state = prefix / "etc" / "branchrange", prefix / "var" / "lib" / "branchrange"

    config_file = etc / "onboard.toml"
    config = load_config(config_file)  # the daemon's own loader accepts it
    assert config.stereo.backend == "sgbm" and config.mavlink.url == "udpout:127.0.0.1:14550"
    assert config.camera.calibration == f"{etc}/SN10012345.conf"
    assert config.log.results_jsonl == f"{state}/results.jsonl"
    text = config_file.read_text()
    assert text.startswith("#:schema config.schema.json\n") and (etc / "config.schema.json").is_file()
    assert "# the companion's UART" not in text and "# the vehicle's SYSID_THISMAV" in text  # comments kept
    assert f"OK: {config_file}" in result.stdout  # `branchrange config check` ran on it

    unit = configparser.ConfigParser(interpolation=None, strict=False)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit_file = prefix / "etc" / "systemd" / "system" / "branchrange-daemon.service"
    unit.read(unit_file)
    service = unit["Service"]
    executable, *arguments = service["ExecStart"].split()
    assert executable == f"{venv}/bin/branchrange" and os.access(executable, os.X_OK)
    assert arguments == ["daemon", "--config", str(config_file)]
    assert service["WorkingDirectory"] == service["ReadWritePaths"] == str(state)
    rules = prefix / "etc" / "udev" / "rules.d" / "99-branchrange-cameras.rules"
    assert rules.read_text() == (ROOT / "deploy" / "99-branchrange-cameras.rules").read_text()

    assert mode(etc) == mode(state) == 0o750  # the configuration may hold a token or a signing key's path
    assert mode(config_file) == 0o640
    assert mode(unit_file) == mode(rules) == mode(etc / "config.schema.json") == 0o644
    assert mode(prefix / "opt" / "branchrange" / "weights") == 0o755


@pytest.mark.skipif(os.name != "posix", reason="a bash script for Linux")
def test_running_it_again_changes_nothing_and_keeps_an_edited_configuration(tmp_path):
    prefix = tmp_path / "prefix"
    premade_venv(prefix)
    assert real_install(tmp_path).returncode == 0
    etc = prefix / "etc" / "branchrange"
    tree = {path: path.read_bytes() for path in prefix.rglob("*") if path.is_file() and ".venv" not in path.parts}

    again = real_install(tmp_path)
    assert again.returncode == 0, again.stderr
    assert {path: path.read_bytes() for path in tree} == tree and not (etc / "onboard.toml.new").exists()

    edited = (etc / "onboard.toml").read_text().replace("max_disp = 128", "max_disp = 96")
    (etc / "onboard.toml").write_text(edited)
    third = real_install(tmp_path)
    assert third.returncode == 0, third.stderr
    assert (etc / "onboard.toml").read_text() == edited  # the operator's edit survives
    assert (etc / "onboard.toml.new").read_bytes() == tree[etc / "onboard.toml"]
    assert "onboard.toml differs from this install's" in third.stdout


@pytest.mark.skipif(os.name != "posix", reason="a bash script for Linux")
def test_the_camera_factory_file_is_placed_beside_the_configuration_which_names_it(tmp_path, shared_data):
    prefix = tmp_path / "prefix"
    premade_venv(prefix)
    factory_file = shared_data / "calibration" / "zed" / "SN1010.conf"
    result = real_install(tmp_path, "--calibration", factory_file)
    assert result.returncode == 0, result.stdout + result.stderr
    placed = prefix / "etc" / "branchrange" / "SN1010.conf"
    assert placed.read_bytes() == factory_file.read_bytes() and mode(placed) == 0o640
    assert load_config(prefix / "etc" / "branchrange" / "onboard.toml").camera.calibration == str(placed)


@pytest.mark.skipif(os.name != "posix", reason="a bash script for Linux")
def test_a_configuration_the_daemon_would_refuse_stops_the_install_with_its_problems(tmp_path):
    premade_venv(tmp_path / "prefix")
    result = real_install(tmp_path, "--set", "stereo.max_disp=100")
    assert result.returncode == 1
    assert "stereo.max_disp" in result.stdout + result.stderr and "has problems" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.skipif(os.name != "posix", reason="a bash script for Linux")
def test_weights_that_are_not_the_released_file_stop_the_install(tmp_path):
    """A configuration naming EMCStereo weights (on the CPU here): the file given is checked by its SHA-256."""
    premade_venv(tmp_path / "prefix")
    config = tmp_path / "emcstereo_cpu.toml"
    config.write_text(
        '[stereo]\nbackend = "emcstereo"\nweights = "/opt/branchrange/weights/emcstereo_virtualtree_best.pth"\n'
        'device = "cpu"\n'
    )
    download = tmp_path / "download"
    download.mkdir()
    (download / "emcstereo_virtualtree_best.pth").write_bytes(b"an interrupted download")
    result = real_install(tmp_path, "--config", config, "--weights-from", download)
    assert result.returncode == 1 and "is not the released emcstereo_virtualtree_best.pth" in result.stderr
    assert "matches no registered weights" in result.stderr  # emcstereo weights verify said why
    assert not (tmp_path / "prefix" / "opt" / "branchrange" / "weights" / "emcstereo_virtualtree_best.pth").exists()
    assert not (tmp_path / "prefix" / "etc" / "branchrange" / "onboard.toml").exists()  # stopped before the config


def test_the_jetson_container_and_the_install_pair_torch_and_configuration_alike():
    """Both take the CUDA configuration only with a CUDA torch, and give the CPU one the Jetson's UART."""
    onboard, cpu = load_config(ROOT / "deploy" / "onboard.toml"), load_config(ROOT / "deploy" / "onboard_cpu.toml")
    assert (onboard.stereo.device, cpu.stereo.device) == ("cuda", "cpu")
    script_uart = re.search(r"^readonly JETSON_UART=(\S+)$", SCRIPT.read_text(), re.MULTILINE).group(1)
    assert script_uart == onboard.mavlink.url
    docker = (ROOT / "deploy" / "Dockerfile.jetson").read_text()
    choice = re.search(
        r"if \.venv/bin/python -c '(.*?)'; then\s*\\\s*cp deploy/onboard\.toml /etc/branchrange/onboard\.toml;"
        r"\s*\\\s*else\s*\\\s*sed 's#\^url = \"(.*?)\"#url = \"(.*?)\"#' deploy/onboard_cpu\.toml",
        docker,
    )
    assert choice, "Dockerfile.jetson no longer picks the configuration by its torch"
    cuda_check, replaced, uart = choice.groups()
    script_cuda_check = re.search(r"^CUDA_CHECK='(.*)'$", SCRIPT.read_text(), re.MULTILINE).group(1)
    assert cuda_check == script_cuda_check and "torch.version.cuda is None" in cuda_check
    assert (replaced, uart) == (cpu.mavlink.url, script_uart)
