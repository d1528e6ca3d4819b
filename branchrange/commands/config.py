"""`branchrange config check|show|schema|reference`: the configuration file, checked and explained.

- `check FILE [--set K=V ...]`: every problem at once, each with its key and line; exit 0 when none.
- `show [FILE] [--set K=V ...] [--json]`: every key in effect and where its value came from.
- `schema`: the JSON Schema editors check the TOML with (the package ships it:
  branchrange/config/config.schema.json, `#:schema` line of deploy/*.toml).
- `reference`: the Markdown reference of every key (docs/configuration.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from branchrange.commands.exit_codes import BAD_INPUT, DONE

if TYPE_CHECKING:
    from branchrange.config.check import ConfigCheck, ConfigProblem

EPILOG = f"""exit codes:
  {DONE}  the configuration is valid (check), or was printed (show, schema, reference)
  {BAD_INPUT}  the configuration has problems (each printed with its key and line) or cannot be read"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `config` and its subcommands to the `branchrange` command."""
    group = subparsers.add_parser(
        "config",
        help="check a configuration file, show the one in effect, print its schema or reference",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = group.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    for name, func, help_text in (
        ("check", run_check, "check FILE: every problem with its key and line"),
        ("show", run_show, "the configuration in effect: every key, its value and its source"),
    ):
        p = sub.add_parser(
            name,
            help=help_text,
            description=help_text,
            epilog=EPILOG,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        if name == "show":  # no file: what the defaults and --set give
            p.add_argument("file", nargs="?", help="the TOML configuration (see deploy/*.toml); none: the defaults")
        else:
            p.add_argument("file", help="the TOML configuration (see deploy/*.toml)")
        p.add_argument(
            "--set",
            action="append",
            default=[],
            metavar="SECTION.KEY=VALUE",
            help="override one key as the daemon's --set does (repeatable), e.g. --set stereo.max_disp=128",
        )
        p.set_defaults(func=func)
    sub.choices["show"].add_argument("--json", action="store_true", help="print JSON: key → {value, source}")
    sub.add_parser("schema", help="print the configuration's JSON Schema").set_defaults(func=run_schema)
    sub.add_parser("reference", help="print the Markdown reference of every key").set_defaults(func=run_reference)


def _checked(args: argparse.Namespace) -> ConfigCheck:
    """The `ConfigCheck` of args.file with args.set; a malformed --set is a problem like any other."""
    from branchrange.config.check import FROM_SET, ConfigCheck, ConfigProblem, check_config
    from branchrange.config.loader import parse_override
    from branchrange.core.settings_check import ConfigError

    try:
        overrides = [parse_override(text) for text in args.set]
    except ConfigError as exc:
        return ConfigCheck([ConfigProblem("", str(exc), FROM_SET)])
    return check_config(args.file, overrides)


def _report_problems(file: str | None, problems: list[ConfigProblem]) -> int:
    """Print each problem (stdout) and their count (stderr); the exit status of a bad configuration."""
    for problem in problems:
        print(problem)
    print(
        f"{file or 'the defaults with --set'}: {len(problems)} problem{'s' if len(problems) != 1 else ''}",
        file=sys.stderr,
    )
    return BAD_INPUT


def run_check(args: argparse.Namespace) -> int:
    """Print every problem of the file, or `OK: FILE (N keys)`."""
    result = _checked(args)
    if result.problems:
        return _report_problems(args.file, result.problems)
    print(f"OK: {args.file} ({len(result.sources)} keys)")
    return DONE


def run_show(args: argparse.Namespace) -> int:
    """Print the configuration in effect, each value's source beside it."""
    from branchrange.config.show import as_json, as_toml, effective_settings

    result = _checked(args)
    if result.problems or result.config is None:
        return _report_problems(args.file, result.problems)
    settings = effective_settings(result.config, result.sources)
    if args.json:
        print(json.dumps(as_json(settings), indent=2, ensure_ascii=False))
    else:
        print(f"# {args.file or 'the defaults'} in effect: every key, its source (default, file or --set) after it\n")
        print(as_toml(settings), end="")
    return DONE


def run_schema(args: argparse.Namespace) -> int:
    """Print the JSON Schema (`branchrange config schema > branchrange/config/config.schema.json`)."""
    from branchrange.config.schema import config_schema, schema_text

    print(schema_text(config_schema()), end="")
    return DONE


def run_reference(args: argparse.Namespace) -> int:
    """Print the Markdown reference (`branchrange config reference > docs/configuration.md`)."""
    from branchrange.config.reference import config_reference
    from branchrange.config.schema import config_schema

    print(config_reference(config_schema()), end="")
    return DONE
