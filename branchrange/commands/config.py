"""`branchrange config check|show|schema|reference`: the configuration file, checked and explained.

- `check FILE [--set K=V ...] [--for daemon|serve] [--file-only]`: every problem at once, each with its key
  and line: the file's own, then what the run will need from this machine (files that exist and can be read,
  a token for a public `[api] host`, the CUDA device asked for; `branchrange.config.needs`); exit 0 when
  none.
- `show [FILE] [--set K=V ...] [--json]`: every key in effect and where its value came from.
- `schema`: the JSON Schema editors check the TOML with (the package ships it:
  branchrange/core/schemas/config.schema.json, `#:schema` line of deploy/*.toml).
- `reference`: the Markdown reference of every key (docs/configuration.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import TYPE_CHECKING

from branchrange.commands.exit_codes import BAD_INPUT, DONE

if TYPE_CHECKING:
    from branchrange.config.check import ConfigCheck, ConfigProblem

#: the commands whose run `check --for` checks the needs of (`branchrange.config.needs.unmet_needs`)
RUN_COMMANDS = ("daemon", "serve")

EPILOG = f"""exit codes:
  {DONE}  the configuration is valid (check), or was printed (show, schema, reference)
  {BAD_INPUT}  the configuration has problems (each printed with its key and line), needs what this machine
     lacks (check without --file-only), or cannot be read"""


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
    sub.choices["check"].add_argument(
        "--for",
        dest="command",
        choices=RUN_COMMANDS,
        help="check what this command's run needs (default: what either would need)",
    )
    sub.choices["check"].add_argument(
        "--file-only",
        action="store_true",
        help="check the file's keys and values only, not this machine (a file meant for another one)",
    )
    sub.add_parser("schema", help="print the configuration's JSON Schema").set_defaults(func=run_schema)
    sub.add_parser("reference", help="print the Markdown reference of every key").set_defaults(func=run_reference)


def _checked(args: argparse.Namespace, *, needs: bool = False) -> ConfigCheck:
    """The `ConfigCheck` of args.file with args.set — with `needs`, also what the run of args.command needs
    from this machine (`check_run`); a malformed --set is a problem like any other."""
    from branchrange.config.check import FROM_SET, ConfigCheck, ConfigProblem, check_config
    from branchrange.config.loader import parse_override
    from branchrange.config.needs import TOKEN_ENV, check_run
    from branchrange.core.settings_check import ConfigError

    try:
        overrides = [parse_override(text) for text in args.set]
    except ConfigError as exc:
        return ConfigCheck([ConfigProblem("", str(exc), FROM_SET)])
    if needs:
        return check_run(args.file, overrides, args.command, os.environ.get(TOKEN_ENV, ""))
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
    """Print every problem of the file and, unless --file-only, of the run's needs; or `OK: FILE (N keys)`."""
    result = _checked(args, needs=not args.file_only)
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
    """Print the JSON Schema (`branchrange config schema > branchrange/core/schemas/config.schema.json`)."""
    from branchrange.config.schema import config_schema, schema_text

    print(schema_text(config_schema()), end="")
    return DONE


def run_reference(args: argparse.Namespace) -> int:
    """Print the Markdown reference (`branchrange config reference > docs/configuration.md`)."""
    from branchrange.config.reference import config_reference
    from branchrange.config.schema import config_schema

    print(config_reference(config_schema()), end="")
    return DONE
