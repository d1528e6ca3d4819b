"""What the pipeline around the network costs at HD720, as a share of the network's own time.

One synthetic 1280×720 scene (stereo.synth) goes through `branchrange.core.pipeline.Pipeline` with a
raw ZED calibration (so rectification runs), the emcstereo backend (fast path, random weights)
and the scene's instance mask; the JSON serialisation of the result is timed too. Prints each
stage's median milliseconds and `(everything − network) / network`; the target is ≤ 10 %. `--json` also
writes them, with the CPU (`machine.py`) and the settings.

    .venv/bin/python benchmarks/pipeline_overhead.py --repeats 3 [--json out/pipeline_overhead.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from machine import cpu_name  # a script's own folder is on its import path

CALIBRATION = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "calibration" / "zed" / "SN1010.conf"


class RecordingBackend:
    """Passes frames to a backend and keeps the timing of the last result (the network's own time)."""

    def __init__(self, backend: object) -> None:
        self.backend = backend
        self.name, self.max_disparity = backend.name, backend.max_disparity
        self.last_timing_ms: dict[str, float] = {}

    def compute(self, left: object, right: object) -> object:
        result = self.backend.compute(left, right)
        self.last_timing_ms = result.timing_ms
        return result


def main(argv: list[str] | None = None) -> int:
    """Time the pipeline's stages on one HD720 frame `repeats` times after a warm-up."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, help="also write the medians here")
    args = parser.parse_args(argv)

    import torch

    from branchrange.core.pipeline import Pipeline
    from camera import load_calibration
    from stereo.backends.emcstereo import EMCStereoBackend
    from stereo.model import EMCStereo
    from stereo.synth import SynthCamera, render_scene

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    scene = render_scene(0, SynthCamera.zed_mini(1280, 720))
    backend = RecordingBackend(EMCStereoBackend(EMCStereo()))
    pipeline = Pipeline(calibration=load_calibration(CALIBRATION, "HD"), backend=backend)
    rows: list[dict[str, float]] = []
    for run in range(args.repeats + 1):
        start = time.perf_counter()
        result = pipeline.process(scene.left, scene.right, mask=scene.instance_mask, index=run)
        json.dumps(result.to_json_dict())
        wall = (time.perf_counter() - start) * 1e3
        rows.append({"wall": wall, "network": backend.last_timing_ms["network"], **result.timing_ms})
    rows = rows[1:]
    stages = sorted({key for row in rows for key in row})
    medians = {key: statistics.median(row.get(key, 0.0) for row in rows) for key in stages}
    print(f"CPU: {cpu_name()}; {args.threads} threads, median of {args.repeats} runs after a warm-up")
    for key in stages:
        print(f"{key:<12} {medians[key]:10.1f} ms")
    around = medians["wall"] - medians["network"]
    print(
        f"around the network (wall − network, incl. serialisation): {around:.1f} ms = "
        f"{around / medians['network']:.1%} of the network's {medians['network']:.0f} ms"
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {
            "cpu": cpu_name(),
            "threads": args.threads,
            "repeats": args.repeats,
            "median_ms": medians,
            "around_network_share": around / medians["network"],
        }
        args.json.write_text(json.dumps(report, indent=2), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
