"""`config check`, `daemon` and `serve` check what the run will need from the machine (issue 49): each shipped
deploy file, installed with everything it names, passes; broken each way a file on a drone breaks — a missing
calibration, weights or bundle, a public API without a token, a results log it cannot write, a CUDA device
that is not there, a `--set` that puts another key out of range — it fails naming the key at fault and where
it was written; the daemon and the service list every problem at once and exit 2, which the systemd unit
does not restart on."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import pytest

from branchrange.cli import main
from branchrange.commands.exit_codes import BAD_INPUT, DONE
from branchrange.config.check import check_config
from branchrange.config.loader import Config
from branchrange.config.needs import TOKEN_ENV, open_bind_refusal, unmet_needs

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
DEPLOY_FILES = ("onboard.toml", "onboard_cpu.toml", "onboard_gpu.toml", "serve.toml")
#: an absolute path a deploy file names on the drone (/etc/branchrange/…, /opt/…, /var/lib/…)
INSTALLED_PATH = re.compile(r'"(/(?:etc|opt|var/lib)/branchrange/[^"]+)"')


@pytest.fixture(autouse=True)
def machine(monkeypatch):
    """A machine with CUDA for torch and onnxruntime (the test machine's own does not decide the outcome) and no
    token in the environment."""
    import torch

    from stereo.onnx_runtime import import_onnxruntime

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    gpu_providers = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    monkeypatch.setattr(import_onnxruntime(), "get_available_providers", lambda: gpu_providers)
    monkeypatch.delenv(TOKEN_ENV, raising=False)


def installed(tmp_path: Path, name: str) -> Path:
    """deploy/NAME as on a machine that has everything it names: its files in `tmp_path`, a token for a
    public API."""
    text = (DEPLOY / name).read_text(encoding="utf-8")
    for original in INSTALLED_PATH.findall(text):
        local = tmp_path / Path(original).name
        if local.suffix != ".jsonl":  # the results log is created by the run
            local.write_bytes(b"stand-in")
        text = text.replace(original, str(local))
    path = tmp_path / name
    path.write_text(text.replace('token = ""', 'token = "s3cret"'), encoding="utf-8")
    return path


def check(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str], str]:
    """`branchrange config check ARGV`: its status, the problems it printed, its summary on stderr."""
    status = main(["config", "check", *argv])
    out, err = capsys.readouterr()
    return status, out.splitlines(), err


def _line_of(path: Path, prefix: str, after: int = 0) -> int:
    """The first 1-based line of `path` after line `after` that starts with `prefix`."""
    return next(n for n, line in enumerate(path.read_text().splitlines(), 1) if n > after and line.startswith(prefix))


def _edit(path: Path, old: str, new: str) -> None:
    """Replace the first `old` of the file `path` (which must hold it) by `new`."""
    text = path.read_text(encoding="utf-8")
    assert old in text
    path.write_text(text.replace(old, new, 1), encoding="utf-8")


# Each way a deploy file breaks: (the file, how) → (extra `config check` arguments, the key, where it is written).
def missing_calibration(path: Path) -> tuple[list[str], str, str]:
    (path.parent / "SN10012345.conf").unlink()
    return [], "camera.calibration", f"{path}:{_line_of(path, 'calibration =')}"


def missing_weights(path: Path) -> tuple[list[str], str, str]:
    (path.parent / "emcstereo_virtualtree_best.pth").unlink()
    return [], "stereo.weights", f"{path}:{_line_of(path, 'weights =')}"


def missing_bundle(path: Path) -> tuple[list[str], str, str]:
    _edit(path, "[segmenter.learned]\n", f'[segmenter.learned]\nmodel = "{path.parent / "tuned_bundle"}"\n')
    return [], "segmenter.learned.model", f"{path}:{_line_of(path, 'model =')}"


def public_api_without_token(path: Path) -> tuple[list[str], str, str]:
    text = path.read_text(encoding="utf-8")
    path.write_text(text.replace('host = "127.0.0.1"', 'host = "0.0.0.0"').replace('token = "s3cret"', 'token = ""'))
    return [], "api.host", f"{path}:{_line_of(path, 'host =')}"


def range_broken_by_set(path: Path) -> tuple[list[str], str, str]:
    return ["--set", "cutpoints.min_range_m=20"], "cutpoints.min_range_m", "--set"  # beyond max_range_m = 10


def no_cuda(path: Path) -> tuple[list[str], str, str]:
    import torch

    torch.cuda.is_available = lambda: False  # restored by the `machine` fixture's monkeypatch
    return [], "stereo.device", f"{path}:{_line_of(path, 'device =')}"


def no_gpu_onnxruntime(path: Path) -> tuple[list[str], str, str]:
    from stereo.onnx_runtime import import_onnxruntime

    import_onnxruntime().get_available_providers = lambda: ["CPUExecutionProvider"]  # restored by `machine`
    line = _line_of(path, "device =", after=_line_of(path, "[segmenter.learned]"))
    return [], "segmenter.learned.device", f"{path}:{line}"


def unwritable_results(path: Path) -> tuple[list[str], str, str]:
    blocker = path.parent / "not_a_folder"
    blocker.write_text("")
    _edit(path, str(path.parent / "results.jsonl"), str(blocker / "results.jsonl"))
    return [], "log.results_jsonl", f"{path}:{_line_of(path, 'results_jsonl =')}"


BREAKAGES: list[tuple[str, Callable[[Path], tuple[list[str], str, str]]]] = [
    *[(name, missing_calibration) for name in ("onboard.toml", "onboard_cpu.toml", "onboard_gpu.toml")],
    *[(name, missing_weights) for name in ("onboard.toml", "onboard_gpu.toml")],
    *[(name, missing_bundle) for name in DEPLOY_FILES],
    *[(name, public_api_without_token) for name in DEPLOY_FILES],
    *[(name, range_broken_by_set) for name in DEPLOY_FILES],
    *[(name, no_cuda) for name in ("onboard.toml", "onboard_gpu.toml")],
    ("onboard_gpu.toml", no_gpu_onnxruntime),
    *[(name, unwritable_results) for name in ("onboard.toml", "onboard_cpu.toml", "onboard_gpu.toml")],
]


@pytest.mark.parametrize("name", DEPLOY_FILES)
def test_each_deploy_file_passes_where_everything_it_names_is_there(capsys, tmp_path, name):
    path = installed(tmp_path, name)
    status, out, _ = check(capsys, str(path))
    assert (status, len(out)) == (DONE, 1) and out[0].startswith(f"OK: {path} (")


@pytest.mark.parametrize("name, breakage", BREAKAGES, ids=lambda v: getattr(v, "__name__", v))
def test_config_check_fails_each_broken_deploy_file_naming_the_key(capsys, tmp_path, name, breakage):
    path = installed(tmp_path, name)
    extra, key, where = breakage(path)
    status, out, err = check(capsys, str(path), *extra)
    assert status == BAD_INPUT and err == f"{path}: 1 problem\n"
    assert out[0].startswith(f"{where}: {key} = "), out


def test_a_cross_key_problem_names_the_key_that_was_set_not_its_default_partner(capsys, tmp_path):
    status, out, _ = check(capsys, str(installed(tmp_path, "onboard.toml")), "--set", "cutpoints.min_range_m=20")
    assert status == BAD_INPUT
    assert out == [
        "--set: cutpoints.min_range_m = 20 conflicts with cutpoints.max_range_m (its default): "
        "cutpoints.max_range_m = 10.0: expected > min_range_m (20.0 m), a distance in metres from 0 to 655 m"
    ]
    written = tmp_path / "range.toml"  # both written in the file: the check's own key, at its line
    written.write_text("[cutpoints]\nmin_range_m = 20.0\nmax_range_m = 10.0\n")
    assert check_config(written).problems[0].where == f"{written}:3"
    (problem,) = check_config(written, [("cutpoints.min_range_m", 12.5)]).problems  # the file's value, --set's fault
    assert (problem.key, problem.where) == ("cutpoints.min_range_m", "--set")
    assert problem.message.startswith("cutpoints.min_range_m = 12.5 conflicts with cutpoints.max_range_m (the file's)")


def test_the_daemon_reports_every_problem_at_once_and_exits_2(capsys, tmp_path):
    path = installed(tmp_path, "onboard.toml")
    for breakage in (missing_calibration, missing_weights, public_api_without_token, no_cuda):
        breakage(path)
    status = main(["daemon", "--config", str(path), "--set", "cutpoints.min_range_m=20"])
    err = capsys.readouterr().err.splitlines()
    assert status == 2
    keys = ("cutpoints.min_range_m", "camera.calibration", "stereo.weights", "stereo.device", "api.host")
    assert [line.split(": ")[2].split(" = ")[0] for line in err[:-1]] == list(keys)
    assert all(line.startswith("branchrange daemon: ") for line in err)
    assert err[-1] == "branchrange daemon: 5 configuration problems; nothing started"


def test_the_daemon_exits_2_on_a_missing_calibration_which_restarting_cannot_fix(capsys, tmp_path):
    path = installed(tmp_path, "onboard_cpu.toml")
    missing_calibration(path)
    assert main(["daemon", "--config", str(path)]) == 2
    assert "camera.calibration = " in capsys.readouterr().err
    unit = (DEPLOY / "branchrange-daemon.service").read_text(encoding="utf-8")
    assert re.search(r"^RestartPreventExitStatus=2$", unit, re.MULTILINE)


def test_serve_lists_its_problems_and_takes_the_token_from_the_environment(capsys, tmp_path, monkeypatch):
    path = installed(tmp_path, "serve.toml")
    public_api_without_token(path)
    missing_bundle(path)
    assert main(["serve", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert "segmenter.learned.model = " in err and "api.host = '0.0.0.0': refusing to serve on 0.0.0.0" in err
    assert err.endswith("branchrange serve: 2 configuration problems; nothing started\n")
    monkeypatch.setenv(TOKEN_ENV, "from-the-unit")
    status, out, _ = check(capsys, str(path))
    assert status == BAD_INPUT and [line.split(": ")[1].split(" = ")[0] for line in out] == ["segmenter.learned.model"]


def test_the_api_is_a_need_of_the_daemon_only_when_it_serves_it(capsys, tmp_path):
    path = installed(tmp_path, "onboard.toml")
    public_api_without_token(path)
    _edit(path, "enabled = true                   # /latest", "enabled = false                  # /latest")
    assert check(capsys, str(path), "--for", "daemon")[0] == DONE
    status, out, _ = check(capsys, str(path), "--for", "serve")
    assert status == BAD_INPUT and len(out) == 1 and out[0].split(": ")[1].startswith("api.host = ")
    assert check(capsys, str(path), "--file-only")[0] == DONE  # a file meant for another machine


def test_the_defaults_need_nothing_a_machine_may_lack():
    """What `check_run` relies on to check the needs of a file with other problems: a section that failed
    stands in at its defaults."""
    assert unmet_needs(Config()) == []


@pytest.mark.parametrize(
    "host, token, refused",
    [("127.0.0.1", "", False), ("::1", "", False), ("localhost", "", False), ("0.0.0.0", "tok", False)]
    + [("192.168.1.5", "", True), ("0.0.0.0", "", True), ("drone.local", "", True)],
)
def test_only_loopback_may_serve_without_a_token(host, token, refused):
    assert bool(open_bind_refusal(host, token)) == refused


@pytest.mark.parametrize(
    "settings, key, says",
    [
        (lambda tmp: {"segmenter": {"model": f"onnx:{tmp}/yolo.onnx"}}, "segmenter.model", "no such file (your ONNX"),
        (
            lambda tmp: {"segmenter": {"model": f"learned:{tmp}/b"}},
            "segmenter.model",
            "no such file or folder (a bundle",
        ),
        (lambda tmp: {"segmenter": {"model": f"onnx:{tmp}"}}, "segmenter.model", "a folder, expected a file"),
        (lambda tmp: {"mavlink": {"signing_key_file": f"{tmp}/m.key"}}, "mavlink.signing_key_file", "no such file"),
        (lambda tmp: {"log": {"results_jsonl": str(tmp)}}, "log.results_jsonl", "a folder, expected a file name"),
        (lambda tmp: {"stereo": {"backend": "onnx", "weights": f"{tmp}/s.onnx"}}, "stereo.weights", "no such file"),
    ],
)
def test_each_path_the_run_reads_or_writes_is_a_need(tmp_path, settings, key, says):
    from branchrange.config.loader import config_from_dict

    ((found, message),) = unmet_needs(config_from_dict(settings(tmp_path)), "daemon")
    assert found == key and says in message and message.startswith(f"{key} = ")


def test_serve_has_no_camera_to_need(tmp_path):
    from branchrange.config.sections import CameraConfig

    cfg = Config(camera=CameraConfig(calibration=str(tmp_path / "SN1.conf")))
    assert [key for key, _ in unmet_needs(cfg, "daemon")] == ["camera.calibration"]
    assert unmet_needs(cfg, "serve") == []
