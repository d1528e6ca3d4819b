"""`branchrange serve`: the HTTP service (POST /estimate, /disparity; GET /health, /version, /metrics)."""

from __future__ import annotations

import argparse
import dataclasses
import ipaddress
import os
import sys

from branchrange.commands.config_args import add_config_arguments, config_from_args

#: Environment variable read (here, at the command line layer only) when the config has no token.
TOKEN_ENV = "BRANCHRANGE_API_TOKEN"


class ServeError(ValueError):
    """A service setting that must not be used (e.g. a public address without a token)."""


def is_loopback(host: str) -> bool:
    """Whether `host` names this machine only (localhost, 127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: str) -> None:
    """Refuse a non-loopback address without a bearer token: the API would be open to the network."""
    if not token and not is_loopback(host):
        raise ServeError(
            f"refusing to serve on {host} without a token: set [api] token or {TOKEN_ENV}, or bind 127.0.0.1"
        )


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `serve` to the `branchrange` command."""
    p = subparsers.add_parser("serve", help="run the HTTP service", description=__doc__)
    add_config_arguments(p, required=False, sections="[api], [stereo], [roi], [cutpoints], [masks], [segmenter], [log]")
    p.add_argument("--host", help="address to bind (overrides api.host)")
    p.add_argument("--port", type=int, help="TCP port (overrides api.port)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Load the config, check the bind address, build the app and serve until interrupted."""
    import uvicorn

    from api import create_app
    from api.estimator import PipelineEstimator
    from branchrange.config.loader import pipeline_config
    from branchrange.core.settings_check import ConfigError

    try:
        cfg = config_from_args(args, {"api.host": args.host, "api.port": args.port})
        api = dataclasses.replace(cfg.api, token=cfg.api.token or os.environ.get(TOKEN_ENV, ""))
        check_bind(api.host, api.token)
    except (ConfigError, ServeError) as exc:
        print(f"branchrange serve: {exc}", file=sys.stderr)
        return 2
    estimator = PipelineEstimator(pipeline_config(cfg))
    try:
        estimator.backend()  # a missing checkpoint or an unusable max_disp fails now, not on every request
        estimator.segmenter()  # so does an unreadable [segmenter] model
    except ValueError as exc:
        print(f"branchrange serve: {exc}", file=sys.stderr)
        return 2
    app = create_app(api, estimator)
    uvicorn.run(app, host=api.host, port=api.port, log_level=cfg.log.level.lower())
    return 0
