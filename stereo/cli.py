"""The `emcstereo` command: the network's tools (params, weights, synth, train, evaluate, export …).

Each subcommand lives in its own module and exposes `register(subparsers)`, which adds its parser
and sets `func(args) -> int`. `branchrange.cli` builds the application's command the same way.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import sys
from collections.abc import Sequence

#: Subcommand modules, in the order `--help` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "stereo.commands.params",
    "stereo.commands.weights",
    "stereo.commands.synth",
    "stereo.commands.train",
    "stereo.commands.finetune",
    "stereo.commands.evaluate",
    "stereo.commands.export",
)


def package_version() -> str:
    """The installed `branchrange` distribution's version (both commands ship in it)."""
    try:
        return importlib.metadata.version("branchrange")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "0+unknown"


def build_parser(prog: str, description: str, modules: Sequence[str]) -> argparse.ArgumentParser:
    """A parser with `--version` whose subcommands are registered by the given modules."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--version", action="version", version=f"{prog} {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in modules:
        importlib.import_module(name).register(sub)
    return parser


def run(prog: str, description: str, modules: Sequence[str], argv: list[str] | None) -> int:
    """Parse `argv`, run the chosen subcommand and return its exit status."""
    args = build_parser(prog, description, modules).parse_args(argv)
    return int(args.func(args) or 0)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `emcstereo` console script."""
    return run("emcstereo", __doc__.splitlines()[0], COMMAND_MODULES, argv)


if __name__ == "__main__":
    sys.exit(main())
