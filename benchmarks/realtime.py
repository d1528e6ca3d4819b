"""Real-time onboard benchmark: a flight sequence replayed at its own frame rate through the daemon.

Each frame is released at its recorded timestamp (as a 15 fps camera would deliver it; a frame that
cannot be on time is dropped: `camera.sources.ReplaySource`). The frames are decoded into memory before the
clock starts (`camera.sources.PreloadedReplay`: a camera delivers raw frames, so the figures are the loop's
alone, not the replay's PNG decoding, a quarter of a 2-core machine's CPU); `--decode-on-the-fly` decodes
each frame ahead of its release instead, as the plain replay does. Each frame goes through the daemon's own
code path — `branchrange.onboard.daemon.Daemon` with its capture, stereo and geometry+send threads, the
pipeline of `branchrange.core.frame_results.pipeline_for` and a real `MavlinkRelay` sending to a UDP
socket on 127.0.0.1 — on `--threads` CPU threads (OpenCV and torch). Nothing waits for the slow
stage: frames the daemon has no time for are dropped, as onboard.

Settings: `--config FILE` is a deploy TOML (e.g. deploy/onboard_cpu.toml) read by the daemon's own
loader with the daemon's precedence (`branchrange.commands.config_args`: the file, then
`--max-disp` / `--max-result-age-s`, then every `--set`); without it the defaults, with
`stereo.max_disp = 128`. Only what ties the daemon to its hardware is replaced: `camera.source` (the
recording, with its own calibration), `mavlink.url` (the UDP socket), `log.results_jsonl` and the
API (off); the mount, `[mavlink]`, `[tracking]` and every pipeline section stay as the file says.

Modes (`--modes`, comma-separated; default `config,full-sgbm` with `--config`, else the last three):
- `config`      — the stereo settings as configured (the shipped file as it is);
- `full-sgbm`   — whole-frame SGBM at full resolution (`stereo.mode = "full"`): the per-frame baseline;
- `roi-sgbm`    — coarse pass + per-branch full-resolution SGBM regions (`stereo.mode = "roi"`);
- `roi-emcstereo` — coarse SGBM pass + per-branch EMCStereo regions (`--weights`, else random weights: timing only).
`--segmenter truth` uses the sequence's instance masks, `builtin` ignores them and runs the
configured segmenter; `both` runs each mode twice.

Every published result goes to a results log exactly as the daemon writes it (a run header, then
one `branchrange/v1` line per result with the captured frame's index and timestamp): to
`--results-jsonl FILE` (overwritten; one run per mode, in the report's order), else to a temporary
file. The scores are read back from that log by `benchmarks/score_flight.py`'s reader and
`branchrange.offline.flight_score.score_results`, as anyone scoring the file later would.

Keys of `--json FILE` (one entry per mode and segmenter under `modes`, e.g. `modes["config/builtin"]`):
- the keys of `branchrange.offline.flight_score` (`fresh_rate_hz`, `latency_ms`, `frames_released`,
  `frames_processed`, `target_recall`, `right_target_rate`, `false_target_rate`, `target_error_m`,
  `first_result_s`, `keyframe_rate_hz`, `tracked_share`, `track_losses`, `target_error_m_by_origin`,
  `visibility`);
- `frames_dropped` (camera frames the stereo stage had no time for, plus stereo outputs the
  geometry stage had no time for, plus frames the replay could not release on time: a busy machine's
  decoding), `late` (results already older than `max_result_age_s` when published);
- `stage_ms.<stage>.p50`: per-stage compute time (the result's `timing_ms`);
- `handover_ms.{capture_to_stereo_ms,capture_to_geometry_ms,capture_to_publish_ms}.p50`: when the
  frame reached each thread (the result's `latency`): the waits between the stages;
- `config_sha256`: the effective configuration's hash (its run header in the results log);
- `load_average_1min`: the machine's load when the mode started (shared machines: read the timings by it), `wall_s`;
- `cpu_s`: the process's CPU time (user + system, every thread) while the daemon ran, s, with the stereo workers'
  (`stereo.workers` other than 1: from the clock's start, their start-up and warm-up left out, on Linux);
  `cpu_s_per_fresh_result`: that over the fresh results published (what one result costs, whatever the machine's
  other load);
- `ratio_to_baseline.{fresh_rate,latency_p50}`: against `full-sgbm` with the same segmenter.
Also `cpu` (model and vector extensions), `threads`, `preloaded` (frames decoded ahead), `sequence`, `flight`
(the render options when rendered here), `config` (`path`, `sha256` of the file), `overrides`, `results_jsonl`,
`max_result_age_s`.

Without `--sequence` a flight is rendered once under out/bench (`branchrange synth-flight`, HD720,
15 fps, 3.0 → 0.8 m, seed 1), at `--speed M/S` and `--yaw-rate DEG/S` when given.

    .venv/bin/python benchmarks/realtime.py --json out/realtime.json   # renders a default HD720 flight first
    .venv/bin/python benchmarks/realtime.py --config deploy/onboard_cpu.toml --segmenter builtin --speed 0.8 \\
        --results-jsonl out/realtime.jsonl --json out/realtime_shipped.json
    .venv/bin/python benchmarks/realtime.py --sequence out/flight --modes roi-sgbm --segmenter builtin
    taskset -c 0,1 .venv/bin/python benchmarks/realtime.py --config deploy/onboard_cpu.toml --modes config \
        --segmenter builtin --speed 0.8 --set stereo.workers=0   # the stereo stage in one process per core

The daemon's stereo workers (`stereo.workers` other than 1) are started and run the warm-up frame before
the clock starts, as the daemon's own pipeline does.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from machine import cpu_description, cpu_name, process_stat_fields  # a script's own folder is on its import path
from score_flight import read_logged_runs, recording_view

from branchrange.commands.config_args import add_config_arguments, config_from_args

if TYPE_CHECKING:
    from branchrange.config.loader import Config
    from branchrange.core.frame_result import FrameResult

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = ROOT / "out" / "bench" / "flight_hd720"
#: mode → ([stereo] backend, mode); None: as configured.
MODES: dict[str, tuple[str, str] | None] = {
    "config": None,
    "full-sgbm": ("sgbm", "full"),
    "roi-sgbm": ("sgbm", "roi"),
    "roi-emcstereo": ("emcstereo", "roi"),
}
#: `stereo.max_disp` without `--config` (the benchmark's figures so far; HD720 at 0.32 m).
UNCONFIGURED_MAX_DISP = 128


class UdpSink:
    """A UDP socket on 127.0.0.1 that reads and discards what the relay sends (the flight controller's place)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.datagrams = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        while not self._stop.is_set():
            try:
                self.sock.recv(65536)
                self.datagrams += 1
            except OSError:
                continue

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()


def base_config(args: argparse.Namespace) -> Config:
    """The configuration every mode starts from: `--config`, the flags, `--set`, as the daemon reads them."""
    max_disp = args.max_disp if args.max_disp is not None or args.config else UNCONFIGURED_MAX_DISP
    flags = {"stereo.max_disp": max_disp, "mavlink.max_result_age_s": args.max_result_age_s}
    config: Config = config_from_args(args, flags)
    return config


def run_config(base: Config, mode: str, sequence: Path, port: int, results: Path, weights: str) -> Config:
    """What the daemon runs in `mode`: `base` on the recording (its own calibration), sending to the UDP
    `port`, logging to `results`, no API; the mode's stereo backend and mode (`weights` for EMCStereo)."""
    stereo = base.stereo
    chosen = MODES[mode]
    if chosen is not None:
        backend, stereo_mode = chosen
        stereo = dataclasses.replace(
            stereo, backend=backend, mode=stereo_mode, weights=weights if backend == "emcstereo" else stereo.weights
        )
    return dataclasses.replace(
        base,
        camera=dataclasses.replace(base.camera, source=f"replay:{sequence}", calibration=""),
        stereo=stereo,
        mavlink=dataclasses.replace(base.mavlink, url=f"udpout:127.0.0.1:{port}"),
        api=dataclasses.replace(base.api, enabled=False),
        log=dataclasses.replace(base.log, results_jsonl=str(results), status_interval_s=3600.0),
    )


def flight_path_for(args: argparse.Namespace) -> Path:
    """Where the flight of `--speed` / `--yaw-rate` is rendered (the default flight without them)."""
    suffix = "".join(
        f"_{name}{value:g}" for name, value in (("speed", args.speed), ("yaw", args.yaw_rate)) if value is not None
    )
    return DEFAULT_SEQUENCE.with_name(DEFAULT_SEQUENCE.name + suffix)


def render_flight(path: Path, args: argparse.Namespace) -> None:
    """Render the flight once: `branchrange synth-flight` defaults (HD720, 15 fps, 3.0 → 0.8 m), seed 1."""
    from branchrange.cli import main as branchrange_main

    argv = ["synth-flight", "--out", str(path), "--seed", "1"]
    argv += ["--speed", str(args.speed)] if args.speed is not None else []
    argv += ["--yaw-rate", str(args.yaw_rate)] if args.yaw_rate is not None else []
    print(f"rendering the flight sequence into {path} (once) ...", file=sys.stderr)
    code = branchrange_main(argv)
    if code != 0:
        raise SystemExit(f"synth-flight failed with exit code {code}")


def run_mode(cfg: Config, segmenter: str, preload: bool) -> dict[str, Any]:
    """Replay `cfg.camera.source` in real time through the daemon as `branchrange daemon` builds it (the
    source aside; `preload`: its frames decoded into memory before the clock starts); its results go to
    `cfg.log.results_jsonl`. Returns the daemon's own counters and the process's CPU seconds over the run."""
    from branchrange.config.loader import pipeline_for
    from branchrange.onboard.daemon import Daemon
    from branchrange.onboard.mavlink import CameraMount, MavlinkRelay
    from camera.sources import PreloadedReplay, ReplaySource

    sequence = cfg.camera.source.removeprefix("replay:")
    replay = (PreloadedReplay if preload else ReplaySource)(
        sequence, pace="recorded", ignore_masks=segmenter != "truth"
    )  # opened (and with `preload` decoded) here; its clock starts at the first frame the daemon reads

    probe = ReplaySource(sequence, pace="fast")
    pipeline = pipeline_for(cfg, probe.calibration)
    warm = next(probe)  # build lazily created parts (backends, coarse matchers) before the clock starts
    pipeline.process(warm.left, warm.right, mask=warm.mask if segmenter == "truth" else None)
    pipeline.reset()
    probe.close()
    mount = CameraMount.from_rpy(cfg.camera.mount_rpy_deg, cfg.camera.mount_xyz_m)
    relay = MavlinkRelay(cfg.mavlink, mount, tracking=cfg.tracking) if cfg.mavlink.enabled else None
    daemon = Daemon(
        cfg,
        open_source=lambda: replay,
        pipeline=pipeline,
        relay=relay,
        results_path=cfg.log.results_jsonl,
        pipeline_factory=functools.partial(pipeline_for, cfg, probe.calibration),  # each stereo worker's own
    )
    try:
        # the stereo workers' pipelines too (`stereo.workers`), before the clock starts
        daemon.warm_up(warm if segmenter == "truth" else dataclasses.replace(warm, mask=None))
        load = cpu_description()["load_average_1min"]  # the other users of a shared machine, at the start
        # the workers' start-up and warm-up are not the flight's: their CPU so far is taken off at the end
        cpu_started = process_cpu_s() + sum(child_cpu_s(pid) for pid in daemon.stereo_worker_pids())
        started = time.monotonic()
        daemon.run()
    finally:
        daemon.close()
    return {
        "frames_dropped": int(daemon.dropped + daemon.skipped + daemon.dropped_late),
        "late": daemon.late,
        "wall_s": round(time.monotonic() - started, 2),
        "cpu_s": round(process_cpu_s() - cpu_started, 2),
        "load_average_1min": load,
    }


def process_cpu_s() -> float:
    """CPU time so far, s: this process's (user + system over every thread, native ones included) and its
    ended children's — the stereo workers (`stereo.workers` other than 1) once `daemon.close()` has joined
    them, their whole lifetime (`child_cpu_s` reads what they had used when the clock started)."""
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


def child_cpu_s(pid: int) -> float:
    """The CPU time so far, s, of the running child process `pid` (user + system, every thread), from Linux's
    /proc/PID/stat (fields 14 and 15, in clock ticks); 0 where there is no /proc (the flight's figure then
    includes the workers' start-up)."""
    fields = process_stat_fields(pid)
    return 0.0 if fields is None else (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def random_weights() -> Path:
    """A checkpoint of a randomly initialised EMCStereo (timing only), written once under out/bench."""
    import torch

    from stereo import EMCStereo, save_checkpoint

    path = ROOT / "out" / "bench" / "emcstereo_random.pth"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(0)
        save_checkpoint(EMCStereo(), path)
    print("roi-emcstereo: random weights (timing only; its errors mean nothing)", file=sys.stderr)
    return path


def timings(results: list[FrameResult]) -> dict[str, Any]:
    """Per-stage compute time and per-hand-over wait, p50 (ms), over `results`."""
    from branchrange.offline.flight_score import percentile

    stages: dict[str, list[float]] = {}
    for result in results:
        for stage, ms in result.timing_ms.items():
            stages.setdefault(stage, []).append(ms)
    handovers = ("capture_to_stereo_ms", "capture_to_geometry_ms", "capture_to_publish_ms")
    waits = {key: [getattr(r.latency, key) for r in results if r.latency is not None] for key in handovers}
    return {
        "stage_ms": {stage: {"p50": percentile(values, 50)} for stage, values in sorted(stages.items())},
        "handover_ms": {
            key: {"p50": percentile([v for v in values if v is not None], 50)} for key, values in waits.items()
        },
    }


def ratio(value: float | None, baseline: float | None, digits: int) -> float | None:
    """`value / baseline` rounded, None when either is missing or the baseline is 0."""
    return round(value / baseline, digits) if value is not None and baseline else None


def add_ratios(rows: dict[str, dict[str, Any]], segmenter: str) -> None:
    """`ratio_to_baseline` of every row of `segmenter` against its `full-sgbm` row, when there is one."""
    baseline = rows.get(f"full-sgbm/{segmenter}")
    if baseline is None:
        return
    for name, row in rows.items():
        if name.endswith(f"/{segmenter}"):
            row["ratio_to_baseline"] = {
                "fresh_rate": ratio(row["fresh_rate_hz"], baseline["fresh_rate_hz"], 2),
                "latency_p50": ratio(row["latency_ms"]["p50"], baseline["latency_ms"]["p50"], 3),
            }


def fmt(value: Any, scale: float = 1.0, digits: int = 0) -> str:
    """A number scaled and rounded for the table; "—" for a figure that does not exist."""
    return "—" if value is None else f"{value * scale:.{digits}f}"


def table_cells(row: dict[str, Any]) -> list[tuple[str, str]]:
    """(column header, cell) of one mode's row in the main table: rates, ms, cm, s; "—" where there is nothing."""
    latency, error, first = row["latency_ms"], row["target_error_m"], row["first_result_s"]
    ratios = row.get("ratio_to_baseline", {})
    return [
        ("fresh Hz", fmt(row["fresh_rate_hz"], 1, 2)),
        ("p50 ms", fmt(latency["p50"])),
        ("p95 ms", fmt(latency["p95"])),
        ("max ms", fmt(latency["max"])),
        ("proc", str(row["frames_processed"])),
        ("drop", str(row["frames_dropped"])),
        ("late", str(row["late"])),
        ("err med cm", fmt(error["median"], 100, 1)),
        ("err p90 cm", fmt(error["p90"], 100, 1)),
        ("recall", fmt(row["target_recall"], 1, 2)),
        ("right", fmt(row["right_target_rate"], 1, 2)),
        ("false", fmt(row["false_target_rate"], 1, 2)),
        ("1st med s", fmt(first["median"], 1, 2)),
        ("1st max s", fmt(first["max"], 1, 2)),
        ("found", f"{first['branches_found']}/{first['branches_in_view']}"),
        ("× fresh", fmt(ratios.get("fresh_rate"), 1, 2)),
        ("× p50", fmt(ratios.get("latency_p50"), 1, 2)),
        ("CPU s/fresh", fmt(row["cpu_s_per_fresh_result"], 1, 3)),
        ("load", fmt(row["load_average_1min"], 1, 1)),
    ]


def print_table(report: dict[str, Any]) -> None:
    config = report["config"]
    print(
        f"\nreal-time replay of {report['sequence']} on {report['cpu']}, {report['threads']} threads, "
        f"config {config['path'] if config else 'defaults'}"
        + (f" (sha256 {config['sha256'][:12]}…)" if config else "")
        + f", max_result_age_s {report['max_result_age_s']}, frames "
        + ("decoded into memory before the clock starts" if report["preloaded"] else "decoded on the fly")
    )
    rows = {name: table_cells(row) for name, row in report["modes"].items()}
    headers = [header for header, _ in next(iter(rows.values()), [])]
    widths = [max(len(header), *(len(cells[i][1]) for cells in rows.values())) for i, header in enumerate(headers)]
    line = f"{'mode/segmenter':22} " + " ".join(h.rjust(w) for h, w in zip(headers, widths))
    print(line)
    print("-" * len(line))
    for name, cells in rows.items():
        print(f"{name:22} " + " ".join(cell.rjust(w) for (_, cell), w in zip(cells, widths)))
    print("\nkeyframes and tracking (from each result's `origin`; — : the results do not say):")
    for name, row in report["modes"].items():
        by_origin = row["target_error_m_by_origin"] or {}
        print(
            f"  {name:22} keyframe Hz {fmt(row['keyframe_rate_hz'], 1, 2)}  tracked {fmt(row['tracked_share'], 1, 2)}  "
            f"track losses {fmt(row['track_losses'])}  "
            + "  ".join(
                f"err {kind} med/p90 cm {fmt((by_origin.get(kind) or {}).get('median'), 100, 1)}/"
                f"{fmt((by_origin.get(kind) or {}).get('p90'), 100, 1)}"
                for kind in ("keyframe", "tracked")
            )
        )
    print("\nper-stage p50 (ms):")
    for name, row in report["modes"].items():
        print(f"  {name:22} " + "  ".join(f"{stage} {fmt(v['p50'], 1, 1)}" for stage, v in row["stage_ms"].items()))
    print("\nframe arrival → each hand-over, p50 (ms):")
    for name, row in report["modes"].items():
        print(
            f"  {name:22} "
            + "  ".join(f"{key.removesuffix('_ms')} {fmt(v['p50'], 1, 1)}" for key, v in row["handover_ms"].items())
        )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line (module docstring); `--modes` filled in from `--config` when not given."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", type=Path, help=f"a flight recording (default: render {DEFAULT_SEQUENCE} once)")
    parser.add_argument(
        "--speed", type=float, help="render the flight at this approach speed, m/s (not with --sequence)"
    )
    parser.add_argument(
        "--yaw-rate", type=float, help="render the flight with this yaw sweep, deg/s (synth-flight --yaw-rate)"
    )
    parser.add_argument("--modes", help=f"comma-separated: {', '.join(MODES)} (default: see the module docstring)")
    parser.add_argument("--segmenter", choices=("truth", "builtin", "both"), default="both")
    parser.add_argument(
        "--weights", help="EMCStereo checkpoint for roi-emcstereo (default: random weights, timing only)"
    )
    parser.add_argument(
        "--max-disp", type=int, help=f"stereo.max_disp, px (default: the file's, else {UNCONFIGURED_MAX_DISP})"
    )
    parser.add_argument(
        "--max-result-age-s", type=float, help="mavlink.max_result_age_s (default: the file's, else 0.5)"
    )
    parser.add_argument("--threads", type=int, default=2, help="OpenCV and torch threads")
    parser.add_argument(
        "--decode-on-the-fly",
        action="store_true",
        help="decode each frame ahead of its release (default: every frame decoded into memory first)",
    )
    parser.add_argument("--json", type=Path, help="write the report here")
    parser.add_argument("--results-jsonl", type=Path, help="write every published result here (overwritten)")
    add_config_arguments(parser, required=False, sections="every section, as `branchrange daemon` reads it")
    args = parser.parse_args(argv)
    if args.sequence is not None and (args.speed is not None or args.yaw_rate is not None):
        parser.error("--speed and --yaw-rate render a flight; not with --sequence")
    args.modes = [m.strip() for m in (args.modes or default_modes(args)).split(",") if m.strip()]
    unknown = [m for m in args.modes if m not in MODES]
    if unknown:
        parser.error(f"unknown mode {unknown[0]!r}; expected {', '.join(MODES)}")
    return args


def default_modes(args: argparse.Namespace) -> str:
    """The file as it is and the per-frame baseline with `--config`; else the three stereo set-ups."""
    return "config,full-sgbm" if args.config else "full-sgbm,roi-sgbm,roi-emcstereo"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)

    import cv2
    import torch

    from branchrange.core.settings_check import ConfigError
    from branchrange.offline.flight import FlightTruth
    from branchrange.offline.flight_score import publish_age_s, score_results
    from stereo.weights import sha256_of

    try:
        base = base_config(args)
    except ConfigError as error:
        raise SystemExit(f"realtime.py: {error}") from None
    cv2.setNumThreads(args.threads)
    torch.set_num_threads(args.threads)
    sequence = args.sequence or flight_path_for(args)
    if args.sequence is None and not (sequence / "flight.json").exists():
        render_flight(sequence, args)
    truth = FlightTruth.load(sequence)
    view = recording_view(sequence, base.mavlink.min_distance_m, base.mavlink.max_distance_m)
    segmenters = ["truth", "builtin"] if args.segmenter == "both" else [args.segmenter]
    runs = [(mode, segmenter) for segmenter in segmenters for mode in args.modes]
    weights = (args.weights or str(random_weights())) if "roi-emcstereo" in args.modes else ""
    report: dict[str, Any] = {
        "cpu": cpu_name(),
        "threads": args.threads,
        "preloaded": not args.decode_on_the_fly,
        "sequence": str(sequence),
        "flight": {"speed_mps": args.speed, "yaw_rate_dps": args.yaw_rate} if args.sequence is None else None,
        "config": {"path": args.config, "sha256": sha256_of(Path(args.config))} if args.config else None,
        "overrides": args.set,
        "results_jsonl": str(args.results_jsonl) if args.results_jsonl else None,
        "max_result_age_s": base.mavlink.max_result_age_s,
        "max_disp": base.stereo.max_disp,
        "modes": {},
    }
    with tempfile.TemporaryDirectory() as scratch:
        log = args.results_jsonl or Path(scratch) / "results.jsonl"
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text("")
        sink = UdpSink()
        try:
            counters = []
            for mode, segmenter in runs:
                print(f"{mode}/{segmenter} ...", file=sys.stderr)
                cfg = run_config(base, mode, sequence, sink.port, log, weights)
                counters.append(run_mode(cfg, segmenter, preload=not args.decode_on_the_fly))
        finally:
            sink.close()
        logged = read_logged_runs(log)
    for (mode, segmenter), counted, (header, results) in zip(runs, counters, logged, strict=True):
        scores = score_results(results, truth, view, base.mavlink.max_result_age_s)
        fresh = sum(age <= base.mavlink.max_result_age_s for age in map(publish_age_s, results) if age is not None)
        report["modes"][f"{mode}/{segmenter}"] = {
            **scores,
            **counted,
            "cpu_s_per_fresh_result": round(counted["cpu_s"] / fresh, 4) if fresh else None,
            **timings(results),
            "config_sha256": header["config_sha256"] if header else None,
        }
    for segmenter in segmenters:
        add_ratios(report["modes"], segmenter)
    print_table(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
