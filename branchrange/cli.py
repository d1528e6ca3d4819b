"""The `branchrange` command: the application (demo, estimate, serve, daemon, replay, config, record …).

Each subcommand lives in its own module under `branchrange.commands` and exposes
`register(subparsers)`, which adds its parser and sets `func(args) -> int`.
"""

from __future__ import annotations

import sys

from stereo.cli import run

#: Subcommand modules, in the order `--help` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "branchrange.commands.serve",
    "branchrange.commands.daemon",
    "branchrange.commands.preflight",
    "branchrange.commands.replay",
    "branchrange.commands.export_frames",
    "branchrange.commands.config",
    "branchrange.commands.record",
    "branchrange.commands.bag_from_recording",
    "branchrange.commands.estimate",
    "branchrange.commands.demo",
    "branchrange.commands.evaluate_cuts",
    "branchrange.commands.synth_flight",
    "branchrange.commands.train_segmenter",
)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `branchrange` console script."""
    return run("branchrange", __doc__.splitlines()[0], COMMAND_MODULES, argv)


if __name__ == "__main__":
    sys.exit(main())
