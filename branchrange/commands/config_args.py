"""`--config FILE` and `--set SECTION.KEY=VALUE`: how the commands that read the configuration take it.

Precedence, lowest first: the defaults, the file, the command's own flags (`--source`,
`--max-disp` …, each the shorthand of one key), then every `--set` in order. Each value passes
the same checks as in the file, so an error names the key whatever way it came in.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Mapping
from typing import Any

from branchrange.commands.exit_codes import BAD_INPUT


def add_config_arguments(parser: argparse.ArgumentParser, *, required: bool, sections: str) -> None:
    """Add --config (the TOML file; `sections`: which of its sections the command reads) and --set."""
    parser.add_argument(
        "--config",
        required=required,
        help=f"TOML configuration ({sections}; see deploy/*.toml)" + ("" if required else "; defaults otherwise"),
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one configuration key, the value in TOML syntax (repeatable), e.g. "
        "--set stereo.max_disp=128 --set segmenter.structure.max_range_m=3",
    )


def overrides_from_args(args: argparse.Namespace, flags: Mapping[str, Any] = {}) -> list[tuple[str, Any]]:
    """The overrides of the file: `flags` (dotted key → value; None: the flag was not given), then --set.
    Raises `ConfigError` for a --set that is not SECTION.KEY=VALUE."""
    from branchrange.config.loader import parse_override

    overrides = [(key, value) for key, value in flags.items() if value is not None]
    return overrides + [parse_override(text) for text in args.set]


def config_from_args(args: argparse.Namespace, flags: Mapping[str, Any] = {}) -> Any:
    """The `branchrange.config.loader.Config` of --config, then `flags`, then --set (`overrides_from_args`).
    Raises `ConfigError` naming the key (and the file, for its errors)."""
    from branchrange.config.loader import load_config

    return load_config(args.config, overrides_from_args(args, flags))


def checked_config(args: argparse.Namespace, flags: Mapping[str, Any], command: str) -> tuple[Any, list[str]]:
    """(the `Config` of --config, `flags` and --set, ready for the run of `command`, []) — `api.token` from
    `TOKEN_ENV` when the file has none — or (None, every problem as `WHERE: MESSAGE`): the file's own and
    each need of the run this machine does not meet (`branchrange.config.needs.check_run`)."""
    from branchrange.config.check import FROM_SET
    from branchrange.config.needs import TOKEN_ENV, check_run
    from branchrange.core.settings_check import ConfigError

    try:
        overrides = overrides_from_args(args, flags)
    except ConfigError as exc:
        return None, [f"{FROM_SET}: {exc}"]
    env_token = os.environ.get(TOKEN_ENV, "")
    check = check_run(args.config, overrides, command, env_token)
    if check.config is None:
        return None, [str(problem) for problem in check.problems]
    try:
        api = dataclasses.replace(check.config.api, token=check.config.api.token or env_token)
    except ConfigError as exc:  # a token with stray spaces in the environment
        return None, [f"{TOKEN_ENV}: {exc}"]
    return dataclasses.replace(check.config, api=api), []


def refuse_config(command: str, problems: list[str]) -> int:
    """Print every configuration problem (stderr, systemd's journal) and their count; the exit status of a
    bad configuration, which the daemon's unit does not restart on (`RestartPreventExitStatus=2`)."""
    for problem in problems:
        print(f"branchrange {command}: {problem}", file=sys.stderr)
    count = f"{len(problems)} configuration problem{'s' if len(problems) != 1 else ''}"
    print(f"branchrange {command}: {count}; nothing started", file=sys.stderr)
    return BAD_INPUT
