"""`--config FILE` and `--set SECTION.KEY=VALUE`: how the commands that read the configuration take it.

Precedence, lowest first: the defaults, the file, the command's own flags (`--source`,
`--max-disp` …, each the shorthand of one key), then every `--set` in order. Each value passes
the same checks as in the file, so an error names the key whatever way it came in.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from typing import Any


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


def config_from_args(args: argparse.Namespace, flags: Mapping[str, Any] = {}) -> Any:
    """The `branchrange.config.loader.Config` of --config, then `flags` (dotted key → value; None: the flag
    was not given), then --set. Raises `ConfigError` naming the key (and the file, for its errors)."""
    from branchrange.config.loader import load_config, parse_override

    overrides = [(key, value) for key, value in flags.items() if value is not None]
    return load_config(args.config, overrides + [parse_override(text) for text in args.set])
