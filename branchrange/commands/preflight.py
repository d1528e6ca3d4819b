"""`branchrange preflight`: the ground test before arming, each check with its fix.

Checks, in order: the camera opens and frames arrive at its configured rate; the calibration is this
camera's (size, and serial with --camera-serial); each model loads and its SHA-256 matches; the
camera's frames go through the pipeline within mavlink.max_result_age_s; the MAVLink link: the
autopilot's heartbeat, its type, signing, and the parameters BranchRange needs (read over MAVLink).
See docs/preflight.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys

from branchrange.commands.config_args import add_config_arguments, config_from_args
from branchrange.commands.exit_codes import BAD_INPUT, CHECK_FAILED, DONE

EPILOG = f"""exit codes:
  {DONE}  every check passed: ready to arm
  {BAD_INPUT}  the configuration cannot be read or is invalid; nothing was checked
  {CHECK_FAILED}  at least one check failed (each printed with its fix)"""


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `preflight` to the `branchrange` command."""
    p = subparsers.add_parser(
        "preflight",
        help="ground test before arming: camera, calibration, models, latency, MAVLink, autopilot parameters",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_arguments(p, required=True, sections="every section the daemon reads")
    p.add_argument("--source", help="frame source spec, overrides camera.source (as for `branchrange daemon`)")
    p.add_argument("--mavlink", help="MAVLink connection string, overrides mavlink.url")
    p.add_argument(
        "--camera-serial",
        metavar="SERIAL",
        help="the serial on the camera's label: camera.calibration must be its SN<SERIAL>.conf",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON: {ready, failed, checks: [...]}")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run every check; print the report; 0 when all passed."""
    from branchrange.core.settings_check import ConfigError
    from branchrange.onboard.preflight import run_preflight

    try:
        cfg = config_from_args(args, {"camera.source": args.source, "mavlink.url": args.mavlink})
    except ConfigError as exc:
        print(f"branchrange preflight: {exc}", file=sys.stderr)
        return BAD_INPUT
    logging.basicConfig(level=logging.WARNING, format="%(name)s %(levelname)s %(message)s")  # stdout: the report
    report = run_preflight(cfg, args.camera_serial)
    print(json.dumps(report.to_dict(), indent=1) if args.json else report.text())
    return DONE if report.ready else CHECK_FAILED
