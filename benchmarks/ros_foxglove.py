"""What reading ROS 2 bags and sending to Foxglove cost per frame, against baselines measured in the same run.

One synthetic scene (stereo.synth, `--size`, default 1280×720) is written `--frames` times (fresh
noise each) as our recording (PNG) and as ZED-style bags (MCAP bgra8, SQLite bgra8, MCAP JPEG).
Reading: milliseconds per stereo pair through `open_source` (decode included), ratio to the
recording's PNG read. Foxglove: milliseconds per `FoxgloveSink` call (overlay and disparity JPEG,
scene, result JSON) writing an MCAP, and writing an MCAP while serving one subscribed WebSocket
client on 127.0.0.1, ratio to the pipeline's own frame (SGBM, `--max-disp`) — the share the sink
adds to the daemon's geometry+send thread. Medians over `--repeats` passes after a warm-up.

    .venv/bin/python benchmarks/ros_foxglove.py --json out/ros_foxglove.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

from machine import cpu_name  # a script's own folder is on its import path

ROOT = Path(__file__).resolve().parents[1]


def per_frame_ms(run, frames: int, repeats: int) -> float:
    """Median over `repeats` passes (after one warm-up pass) of a pass's time divided by `frames`, ms."""
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        run()
        times.append((time.perf_counter() - start) * 1e3 / frames)
    return statistics.median(times[1:])


def read_all(spec: str) -> None:
    from camera.sources import open_source

    with open_source(spec, pace="fast") as source:
        for _ in source:
            pass


def subscribed_client(port: int, stop: threading.Event) -> threading.Thread:
    """A WebSocket client on loopback subscribed to every channel, reading until `stop`."""
    from websockets.sync.client import connect

    ready = threading.Event()

    def run() -> None:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5) as ws:
            channels = []
            while not channels:
                message = json.loads(ws.recv(timeout=5))
                channels = message.get("channels", []) if message["op"] == "advertise" else []
            ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [{"id": i, "channelId": c["id"]} for i, c in enumerate(channels)],
                    }
                )
            )
            ready.set()
            while not stop.is_set():
                try:
                    ws.recv(timeout=0.1)
                except TimeoutError:
                    pass

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    ready.wait(10)
    return thread


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT of each view")
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-disp", type=int, default=128)
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args(argv)

    import cv2
    import numpy as np

    from branchrange.config.loader import Config, pipeline_for
    from branchrange.core.frame_results import process_frame
    from branchrange.core.pipeline import StereoConfig
    from branchrange.onboard.foxglove_sink import FoxgloveSink, FoxgloveTargets
    from camera.calibration import from_rectified
    from camera.sources import Recorder, StereoFrame
    from camera.sources.rosbag_writer import write_bag
    from stereo.synth import SynthCamera, render_scene

    cv2.setNumThreads(2)
    width, height = (int(v) for v in args.size.split("x"))
    scene = render_scene(3, SynthCamera.zed_mini(width, height))
    cam = scene.camera
    calibration = from_rectified(cam.focal_px, cam.cx, cam.cy, cam.baseline_m, (width, height))
    rng = np.random.default_rng(0)
    frames = [
        StereoFrame(
            *(np.clip(v + rng.normal(0, 1.0, v.shape), 0, 255).astype(np.uint8) for v in (scene.left, scene.right)),
            1_000_000_000 + i * 66_666_667,
            i,
        )
        for i in range(args.frames)
    ]
    rows: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        with Recorder(work / "rec", calibration=calibration) as recorder:
            for frame in frames:
                recorder.write(frame)
        bags = {
            "rosbag MCAP bgra8": ("mcap", "bgra8"),
            "rosbag SQLite bgra8": ("sqlite3", "bgra8"),
            "rosbag MCAP jpeg": ("mcap", "jpeg"),
        }
        for name, (storage, encoding) in bags.items():
            write_bag(frames, calibration, work / name.replace(" ", "_"), storage=storage, encoding=encoding)
        read_base = per_frame_ms(lambda: read_all(f"replay:{work / 'rec'}"), args.frames, args.repeats)
        rows["recording PNG read (baseline)"] = {"ms": read_base, "ratio": 1.0}
        for name in bags:
            ms = per_frame_ms(
                lambda n=name: read_all(f"rosbag:{work / n.replace(' ', '_')}"), args.frames, args.repeats
            )
            rows[f"{name} read"] = {"ms": ms, "ratio": ms / read_base}

        cfg = Config(stereo=StereoConfig(max_disp=args.max_disp))
        pipeline = pipeline_for(cfg, calibration)
        outputs = []

        def run_pipeline() -> None:
            outputs.clear()
            pipeline.reset()
            for frame in frames:
                outputs.append((process_frame(pipeline, frame), pipeline.last))

        pipe_ms = per_frame_ms(run_pipeline, args.frames, args.repeats)
        rows["pipeline frame, sgbm (baseline)"] = {"ms": pipe_ms, "ratio": 1.0}

        def run_sink(with_server: bool) -> None:
            targets = FoxgloveTargets(mcap=work / "fg.mcap", port=0 if with_server else None)
            with FoxgloveSink(targets) as sink:
                stop = threading.Event()
                client = subscribed_client(sink.port, stop) if with_server else None
                start = time.perf_counter()
                for result, artifacts in outputs:
                    sink(result, artifacts)
                timings.append((time.perf_counter() - start) * 1e3 / len(outputs))
                stop.set()
                if client is not None:
                    client.join(5)

        for name, with_server in (("Foxglove sink, MCAP", False), ("Foxglove sink, MCAP + live client", True)):
            timings: list[float] = []
            for _ in range(args.repeats + 1):
                run_sink(with_server)
            ms = statistics.median(timings[1:])
            rows[name] = {"ms": ms, "ratio": ms / pipe_ms}

    print(
        f"CPU: {cpu_name()}; {width}×{height}, {args.frames} frames, median of {args.repeats} passes; "
        "the machine is shared, so compare the ratios"
    )
    print(f"{'what':<38} {'ms/frame':>9} {'ratio':>7}")
    for name, row in rows.items():
        print(f"{name:<38} {row['ms']:9.1f} {row['ratio']:7.3f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {
                    "cpu": cpu_name(),
                    "size": [width, height],
                    "frames": args.frames,
                    "repeats": args.repeats,
                    "rows": rows,
                },
                indent=2,
            )
            + "\n"
        )
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
