"""How soon targets go out again after the autopilot's link comes back (issue 39: 3–12 s in the soak).

The relay alone (`MavlinkRelay`, the shipped `[tracking]` rules: 3 consistent observations), the autopilot
simulator on loopback hovering, and results published at `--fps` with `--latency-ms` from capture to
publish, each holding the one branch the hover sees (the measurement noise the tracker assumes). Each
episode: targets flowing for `STEADY_S`, then a fault of the link — the autopilot silent for `--silence-s`
(its state stops; the relay goes on without vehicle state), or signing with another key as long — then
the time from the fault's end to the first target the autopilot receives. No CPU load of the pipeline:
this measures the relay's rules, not a machine.

    .venv/bin/python benchmarks/link_recovery.py --episodes 6 --json out/link_recovery.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np
from machine import cpu_name  # a script's own folder is on its import path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the autopilot simulator and result factory the tests use
from autopilot_sim import (  # noqa: E402
    SIM_BASELINE_M,
    SIM_FOCAL_PX,
    AutopilotSim,
    approach_flight,
    camera_point,
    noisy,
)
from result_factory import branch, frame_result  # noqa: E402

from branchrange.config.sections import MavlinkConfig, TrackingConfig  # noqa: E402
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay  # noqa: E402

#: Seconds of targets flowing before each fault.
STEADY_S = 4.0
#: The hovering branch in local NED (m): 1.5 m ahead of the vehicle.
BRANCH_NED = np.array([1.5, 0.1, -0.2])


def publisher(relay: MavlinkRelay, sim: AutopilotSim, fps: float, latency_s: float, stop: threading.Event) -> None:
    """Capture at `fps`, publish each result `latency_s` after its capture, until `stop`."""
    mount, tracking, rng = CameraMount.from_rpy(), TrackingConfig(), np.random.default_rng(0)
    captured = time.monotonic()
    while not stop.wait(max(0.0, captured + latency_s - time.monotonic())):
        cam = noisy(camera_point(sim.pose_at(captured), BRANCH_NED, mount), rng, tracking)
        result = frame_result(
            [branch(0, cam, confidence=0.9)], target_id=0, focal_px=SIM_FOCAL_PX, baseline_m=SIM_BASELINE_M
        )
        relay.publish(result, captured_at=captured)
        captured += 1.0 / fps


def first_target_after(sim: AutopilotSim, at: float, timeout_s: float) -> float | None:
    """Seconds from `at` to the first DEBUG_VECT target the simulator received after it (None: none came)."""
    deadline = at + timeout_s
    while time.monotonic() < deadline:
        for received in sim.of_type("DEBUG_VECT"):
            if received.at >= at and not math.isnan(received.msg.x):
                return received.at - at
        time.sleep(0.02)
    return None


def run(args: argparse.Namespace) -> dict[str, object]:
    key = os.urandom(32)
    key_file = Path(args.out) / "link_recovery.key"
    key_file.parent.mkdir(parents=True, exist_ok=True)
    key_file.write_bytes(key)
    times: dict[str, list[float | None]] = {"silence": [], "wrong_key": []}
    stop = threading.Event()
    with AutopilotSim(approach_flight(0.0), signing_key=key) as sim:
        cfg = MavlinkConfig(url=f"udpout:127.0.0.1:{sim.port}", signing_key_file=str(key_file))
        with MavlinkRelay(cfg, CameraMount.from_rpy()) as relay:
            thread = threading.Thread(target=publisher, args=(relay, sim, args.fps, args.latency_ms / 1000, stop))
            thread.start()
            try:
                for episode in range(args.episodes):
                    for kind in times:
                        time.sleep(STEADY_S)
                        if kind == "silence":
                            sim.silence(args.silence_s)
                        else:
                            sim.wrong_key(os.urandom(32), args.silence_s)
                        time.sleep(args.silence_s)
                        took = first_target_after(sim, time.monotonic(), 15.0)
                        times[kind].append(None if took is None else round(took, 3))
                        print(f"episode {episode + 1}, {kind}: first target after {took} s", file=sys.stderr)
            finally:
                stop.set()
                thread.join()
    summary = {}
    for kind, values in times.items():
        got = sorted(v for v in values if v is not None)
        summary[kind] = {
            "episodes": len(values),
            "none_within_15_s": sum(v is None for v in values),
            "median_s": round(statistics.median(got), 3) if got else None,
            "max_s": got[-1] if got else None,
            "all_s": values,
        }
    return {
        "cpu": cpu_name(),
        "load_1min": os.getloadavg()[0],
        "fps": args.fps,
        "latency_ms": args.latency_ms,
        **summary,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=6, help="faults of each kind (default 6)")
    parser.add_argument("--fps", type=float, default=5.0, help="results a second (default 5)")
    parser.add_argument("--latency-ms", type=float, default=150.0, help="capture → publish (default 150 ms)")
    parser.add_argument("--silence-s", type=float, default=6.0, help="how long each fault lasts (default 6 s)")
    parser.add_argument("--out", default=str(ROOT / "out"), help="folder for the signing key file")
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args(argv)
    result = run(args)
    print(
        f"link recovery on {result['cpu']}, load {result['load_1min']:.1f}, {args.fps} results/s, {args.latency_ms} ms"
    )
    print(f"{'fault':10} {'episodes':>8} {'none':>5} {'median s':>9} {'max s':>6}")
    for kind in ("silence", "wrong_key"):
        row = result[kind]
        print(f"{kind:10} {row['episodes']:8d} {row['none_within_15_s']:5d} {row['median_s']!s:>9} {row['max_s']!s:>6}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
