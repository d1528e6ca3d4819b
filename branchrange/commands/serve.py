"""`branchrange serve`: the HTTP service (POST /estimate, /disparity; GET /health, /version, /metrics)."""

from __future__ import annotations

import argparse

from branchrange.commands.config_args import add_config_arguments, checked_config, refuse_config


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `serve` to the `branchrange` command."""
    p = subparsers.add_parser("serve", help="run the HTTP service", description=__doc__)
    add_config_arguments(p, required=False, sections="[api], [stereo], [roi], [cutpoints], [masks], [segmenter], [log]")
    p.add_argument("--host", help="address to bind (overrides api.host)")
    p.add_argument("--port", type=int, help="TCP port (overrides api.port)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check the config and what the service needs (a token on a public address, its model files: every
    problem at once, exit 2), build the app and serve until interrupted."""
    import uvicorn

    from api import create_app
    from api.estimator import PipelineEstimator
    from branchrange.config.loader import pipeline_config

    cfg, problems = checked_config(args, {"api.host": args.host, "api.port": args.port}, "serve")
    if cfg is None:
        return refuse_config("serve", problems)
    estimator = PipelineEstimator(pipeline_config(cfg))
    try:
        estimator.backend()  # a missing checkpoint or an unusable max_disp fails now, not on every request
        estimator.segmenter()  # so does an unreadable [segmenter] model
    except ValueError as exc:
        return refuse_config("serve", [str(exc)])
    app = create_app(cfg.api, estimator)
    uvicorn.run(app, host=cfg.api.host, port=cfg.api.port, log_level=cfg.log.level.lower())
    return 0
