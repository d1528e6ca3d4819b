"""`branchrange daemon`: camera → cut points → MAVLink + JSONL log (+ /latest, /health, /metrics), onboard."""

from __future__ import annotations

import argparse
import functools
import logging
import signal
import sys
import threading
from typing import TYPE_CHECKING, Any

from branchrange.commands.config_args import add_config_arguments, checked_config, refuse_config

if TYPE_CHECKING:  # imported when the command runs: `branchrange --help` stays fast
    from api.metrics import Metrics
    from branchrange.config.loader import Config
    from branchrange.onboard.daemon import Daemon


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `daemon` to the `branchrange` command."""
    p = subparsers.add_parser("daemon", help="run onboard: camera → cut points → MAVLink", description=__doc__)
    add_config_arguments(p, required=True, sections="every section; see deploy/onboard.toml")
    p.add_argument(
        "--source",
        help="frame source spec, overrides camera.source (zed:0, oak, replay:PATH, rosbag:PATH; a replay in step "
        "with a simulator: replay:PATH?start_at=TIME&start_signal=udp:HOST:PORT)",
    )
    p.add_argument("--mavlink", help="MAVLink connection string, overrides mavlink.url")
    p.add_argument("--max-frames", type=int, help="stop after this many processed frames")
    p.add_argument(
        "--foxglove",
        action="append",
        default=[],
        metavar="ws://HOST:PORT|FILE.mcap",
        help="also send every frame to Foxglove: serve a live WebSocket and/or write an MCAP file "
        "(repeat for both); open with deploy/foxglove_layout.json",
    )
    p.set_defaults(func=run)


def _start_api(cfg: Config, daemon: Daemon, metrics: Metrics) -> tuple[Any, threading.Thread]:
    """uvicorn serving /latest, /health, /metrics in a background thread of this process."""
    import uvicorn

    from api import create_app

    app = create_app(cfg.api, None, state=daemon, metrics=metrics)
    server = uvicorn.Server(uvicorn.Config(app, host=cfg.api.host, port=cfg.api.port, log_level="warning"))
    server.install_signal_handlers = lambda: None  # the daemon owns SIGTERM/SIGINT
    thread = threading.Thread(target=server.run, name="api", daemon=True)
    thread.start()
    return server, thread


def run(args: argparse.Namespace) -> int:
    """Build source, pipeline, relay and log from the config; run until the source ends or a signal."""
    from api.metrics import Metrics
    from branchrange.config.loader import pipeline_for
    from branchrange.onboard.daemon import Daemon, relay_for
    from branchrange.onboard.foxglove_sink import FoxgloveSink, FoxgloveTargetError, parse_targets
    from branchrange.onboard.mavlink import CameraMount
    from branchrange.onboard.mavlink.connection import SigningKeyError
    from camera.sources import SourceError, open_source

    cfg, problems = checked_config(args, {"camera.source": args.source, "mavlink.url": args.mavlink}, "daemon")
    try:
        targets = parse_targets(args.foxglove) if args.foxglove else None
    except FoxgloveTargetError as exc:
        problems.append(str(exc))
    if cfg is None or problems:
        return refuse_config("daemon", problems)
    logging.basicConfig(level=cfg.log.level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    calibration = cfg.camera.calibration or None

    def open_camera() -> Any:
        return open_source(cfg.camera.source, calibration=calibration, pace="recorded")

    first = sink = relay = None
    mount = CameraMount.from_rpy(cfg.camera.mount_rpy_deg, cfg.camera.mount_xyz_m)
    try:
        first = open_camera()
        pipeline = pipeline_for(cfg, first.calibration)
        if cfg.mavlink.enabled:
            relay = relay_for(cfg, mount)
        if targets is not None:
            sink = FoxgloveSink(targets, mount=mount, newest_only=True)
            if relay is not None:
                sink.follow_vehicle(
                    relay.vehicle_pose
                )  # the scene in local NED too, while the autopilot streams its pose
    except (SourceError, SigningKeyError, ValueError) as exc:
        for opened in (first, relay, sink):
            if opened is not None:
                opened.close()
        print(f"branchrange daemon: {exc}", file=sys.stderr)
        return 1
    api = f"http://{cfg.api.host}:{cfg.api.port}" if cfg.api.enabled else "off"
    logging.getLogger("branchrange.daemon").info(
        "starting: mode=%s backend=%s max_disp=%d source=%s mavlink=%s api=%s results=%s foxglove=%s",
        cfg.stereo.mode,
        cfg.stereo.backend,
        cfg.stereo.max_disp,
        cfg.camera.source,
        cfg.mavlink.url if relay else "off",
        api,
        cfg.log.results_jsonl or "off",
        sink.describe() if sink else "off",
    )
    sources = iter([first])  # the first source is the one already opened; reopening opens new ones
    metrics = Metrics()
    daemon = Daemon(
        cfg,
        open_source=lambda: next(sources, None) or open_camera(),
        pipeline=pipeline,
        relay=relay,
        results_path=cfg.log.results_jsonl or None,
        metrics=metrics,
        observers=[sink] if sink is not None else [],
        pipeline_factory=functools.partial(pipeline_for, cfg, first.calibration),  # built again in each stereo worker
    )
    previous = {sig: signal.signal(sig, lambda *_: daemon.stop()) for sig in (signal.SIGTERM, signal.SIGINT)}
    server = thread = None
    if cfg.api.enabled:
        server, thread = _start_api(cfg, daemon, metrics)
    try:
        frames = daemon.run(max_frames=args.max_frames)
    finally:
        daemon.close()
        if sink is not None:
            sink.close()
            logging.getLogger("branchrange.foxglove").info(
                "Foxglove: %d frames sent, %d replaced by newer ones", sink.frames, sink.dropped
            )
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if server is not None:
            server.should_exit = True
            thread.join(timeout=5)
    logging.getLogger("branchrange.daemon").info("stopped after %d frames", frames)
    return 0
