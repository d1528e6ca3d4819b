"""What a run will need from the machine it starts on, checked before it starts: every unmet need at once.

A configuration can be valid (`branchrange.config.check`: types, ranges, the checks between keys)
and still fail the moment the daemon or the service starts: a calibration file, stereo weights or a
segmenter model that is not there, a results log whose folder cannot be written, a public `[api] host`
without a token, a CUDA device on a machine without one. Each used to stop the daemon at the first one
with exit 1, which the systemd unit restarts every 5 s for ever; restarting cannot fix any of them.
So `config check`, `daemon` and `serve` ask `unmet_needs` for all of them, each naming its key, and
the commands exit 2 (a configuration problem: `RestartPreventExitStatus=2`).

What is checked depends on the command ("daemon" or "serve"): the daemon reads the camera's calibration and the
MAVLink signing key and serves the API only when `api.enabled`; `serve` always serves and has no camera;
`config check` without `--for` checks what either would need. Relative paths are resolved against the
working directory, as the run resolves them (the unit's is /var/lib/branchrange).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from branchrange.config.check import ConfigCheck, ConfigProblem, check_config
from branchrange.config.loader import Config, Override, config_from_dict
from branchrange.core.segmentation.learned import SHIPPED_MODELS
from branchrange.core.settings_check import ConfigError
from stereo.backends import WEIGHTED_BACKENDS

#: the environment variable that holds the API token when the configuration has none (read by the commands)
TOKEN_ENV = "BRANCHRANGE_API_TOKEN"
#: (dotted key at fault, message naming it): one unmet need
Need = tuple[str, str]


def is_loopback(host: str) -> bool:
    """Whether `host` names this machine only (localhost, 127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def open_bind_refusal(host: str, token: str) -> str:
    """Why the API must not listen on `host` with bearer token `token` ('' when it may): any address but
    loopback without a token would open it to the network."""
    if token or is_loopback(host):
        return ""
    return f"refusing to serve on {host} without a token: set [api] token or {TOKEN_ENV}, or bind 127.0.0.1"


def _unreadable(path: Path, *, folder_allowed: bool = False) -> str:
    """What is wrong with reading `path` as the run will ('' when nothing): missing, a folder, no permission."""
    if not path.exists():
        return "no such file" + (" or folder" if folder_allowed else "")
    if path.is_dir() and not folder_allowed:
        return "a folder, expected a file"
    if not os.access(path, os.R_OK | (os.X_OK if path.is_dir() else 0)):
        return "not readable by this user (permission denied)"
    return ""


def _readable(key: str, value: str, *, folder_allowed: bool = False, what: str = "") -> Iterator[Need]:
    """The need of `key`, a path the run reads (`what` it is, for the message): it exists and can be read."""
    wrong = _unreadable(Path(value), folder_allowed=folder_allowed)
    if wrong:
        yield key, f"{key} = {value!r}: {wrong}" + (f" ({what})" if what else "")


def _writable_log(key: str, value: str) -> Iterator[Need]:
    """The need of a log file the run appends to: the file writable, or its nearest existing folder
    writable (the run creates the folders below it, `results_log.ResultsLog`)."""
    path = Path(value)
    if path.is_dir():
        yield key, f"{key} = {value!r}: a folder, expected a file name"
        return
    existing = next(p for p in (path, *path.parents) if p.exists())  # "/" or "." at the latest
    if existing == path and not os.access(path, os.W_OK):
        yield key, f"{key} = {value!r}: not writable by this user (the run appends to it)"
    elif existing != path and not (existing.is_dir() and os.access(existing, os.W_OK | os.X_OK)):
        yield (
            key,
            f"{key} = {value!r}: {existing} is not a folder this user can write in (the run creates the log there)",
        )


def _segmenter_model(cfg: Config) -> Iterator[Need]:
    """The need of the segmenter's model: the file or bundle folder `segmenter.model` names, or the learned
    segmenter's `model` (empty: the shipped one of its precision, part of the install)."""
    name = cfg.segmenter.model
    kind, _, path = name.partition(":")
    if kind == "onnx":
        yield from _readable("segmenter.model", path, what="your ONNX model")
    elif kind == "learned" and path:
        yield from _readable("segmenter.model", path, folder_allowed=True, what="a bundle of train-segmenter --coco")
    elif kind == "learned" and cfg.segmenter.learned.model:
        yield from _readable(
            "segmenter.learned.model",
            cfg.segmenter.learned.model,
            folder_allowed=True,
            what="an ONNX model or a bundle folder",
        )
    elif kind == "learned":
        shipped = str(SHIPPED_MODELS[cfg.segmenter.learned.precision])
        yield from _readable("segmenter.model", shipped, what="the shipped model: reinstall the package")
    if kind == "learned" and cfg.segmenter.learned.device != "cpu":
        yield from _segmenter_device(cfg.segmenter.learned.device)


def _segmenter_device(device: str) -> Iterator[Need]:
    """The need of a learned segmenter on a GPU: onnxruntime's provider for `device` (onnxruntime-gpu)."""
    from branchrange.core.segmentation.onnx_model import OnnxSegmenterError, execution_providers
    from stereo.onnx_runtime import import_onnxruntime

    try:
        execution_providers(device, list(import_onnxruntime().get_available_providers()))
    except ImportError:
        yield "segmenter.learned.device", f"segmenter.learned.device = {device!r}: onnxruntime is not installed"
    except OnnxSegmenterError as exc:
        yield "segmenter.learned.device", f"segmenter.learned.device = {device!r}: {exc}"


def _stereo(cfg: Config) -> Iterator[Need]:
    """The needs of a network stereo backend: its weights file, and the device it runs on."""
    if cfg.stereo.backend not in WEIGHTED_BACKENDS:
        return
    yield from _readable("stereo.weights", cfg.stereo.weights, what="the backend's checkpoint")
    if cfg.stereo.device != "cpu":
        from stereo.backends.emcstereo import resolve_device  # torch: imported only when a device is asked for

        try:
            resolve_device(cfg.stereo.device)
        except ValueError as exc:
            yield "stereo.device", f"stereo.device = {cfg.stereo.device!r}: {exc}"


def unmet_needs(cfg: Config, command: str | None = None, env_token: str = "") -> list[Need]:
    """Every need of the run of `command` ("daemon" or "serve"; None: of either) that this machine does not
    meet, in the order of the file's sections; `env_token` is the value of `TOKEN_ENV` the run will see."""
    needs: list[Need] = []
    if command != "serve":
        if cfg.camera.calibration:
            needs += _readable("camera.calibration", cfg.camera.calibration, what="the camera's calibration file")
        if cfg.mavlink.enabled and cfg.mavlink.signing_key_file:
            needs += _readable("mavlink.signing_key_file", cfg.mavlink.signing_key_file, what="the MAVLink key")
    needs += _stereo(cfg)
    needs += _segmenter_model(cfg)
    if cfg.log.results_jsonl:
        needs += _writable_log("log.results_jsonl", cfg.log.results_jsonl)
    if command != "daemon" or cfg.api.enabled:
        refusal = open_bind_refusal(cfg.api.host, cfg.api.token or env_token)
        if refusal:
            needs.append(("api.host", f"api.host = {cfg.api.host!r}: {refusal}"))
    return needs


def _valid_sections(tree: dict[str, Any]) -> Config:
    """The configuration of the sections of TOML `tree` that pass their checks, the others at their defaults
    (which need nothing a machine may lack): a file's other problems do not hide its unmet needs."""
    sections = {}
    for name, table in tree.items():
        try:
            sections[name] = getattr(config_from_dict({name: table}), name)
        except ConfigError:
            continue  # reported by `check_config`
    return Config(**sections)


def check_run(
    path: str | Path | None, overrides: Iterable[Override] = (), command: str | None = None, env_token: str = ""
) -> ConfigCheck:
    """`check_config` of the file `path` with `overrides`, and every `unmet_needs` of `command`'s run, each
    where its key was written; `config` only when there is no problem of either kind."""
    check = check_config(path, overrides)
    if check.places is None:  # the file or the --set could not be read: no keys to go by
        return check
    config = check.config or _valid_sections(check.tree)
    unmet = [
        ConfigProblem(key, message, check.places.of(key)) for key, message in unmet_needs(config, command, env_token)
    ]
    if not unmet:
        return check
    return dataclasses.replace(check, problems=check.problems + sorted(unmet, key=check.places.order), config=None)
