"""Speed of synthetic flight frames (`branchrange synth-flight`) against a still scene rendered in the same run.

Per frame of a flight the tree is not drawn again: its geometry is carried into the frame's
pose and both views are ray-cast (1 ray per pixel side: the left colour pass gives the truth).
The baseline is `render_scene` of the same seed at the same size and supersampling (it also
draws the scene and casts a separate truth pass only when supersampling); the default
`render_scene` (2×2 rays per pixel) is listed too. Frames are taken at the start, middle and
end of a 3.0 → 0.8 m approach (the near end fills the view with trunk). Wall and CPU seconds
are medians over seeds × frames × repeats; the machine's CPU and load are printed, since the
wall time on a shared machine depends on what else runs.

    .venv/bin/python benchmarks/synth_flight_speed.py                      # HD720, 3 seeds, bare + foliage
    .venv/bin/python benchmarks/synth_flight_speed.py --size 640x360 --json out/flight_speed.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

from machine import cpu_name  # benchmarks/ is the script's directory, so on sys.path

from stereo.synth import SynthCamera, render_scene
from stereo.synth.flight import FlightRenderer
from stereo.synth.flight_path import FlightOptions

#: The per-frame budget of the issue: an HD720 frame within a second on 2 cores.
BUDGET_S = 1.0


def timed(call: Callable[[], object]) -> tuple[float, float]:
    """(wall s, CPU s of this process over all threads) of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    call()
    return time.perf_counter() - wall, time.process_time() - cpu


def measure(width: int, height: int, seeds: list[int], repeats: int) -> list[dict[str, object]]:
    """One row per (foliage, configuration): median wall and CPU seconds per frame and the ratio to the baseline."""
    camera = SynthCamera.zed_mini(width, height)
    rows = []
    for foliage in (False, True):
        samples: dict[str, list[tuple[float, float]]] = {}
        for seed in seeds:
            leaves = "sparse" if foliage else "bare"
            calls = {
                "render_scene 1 ray/px (baseline)": [
                    lambda s=seed, f=leaves: render_scene(s, camera, supersample=1, foliage=f)
                ],
                "render_scene 2x2 rays/px (default)": [lambda s=seed, f=leaves: render_scene(s, camera, foliage=f)],
            }
            for blur in (False, True):
                renderer = FlightRenderer(
                    FlightOptions(
                        frames=31,
                        width=width,
                        height=height,
                        seed=seed,
                        foliage=foliage,
                        motion_blur=blur,
                        jitter_deg=1.0,
                        sway_m=0.05,
                    )
                )
                name = f"flight frame{' + motion blur' if blur else ''}"
                calls[name] = [lambda r=renderer, i=index: r.render(i) for index in (0, 15, 30)]
            for _ in range(repeats):
                for name, runs in calls.items():
                    samples.setdefault(name, []).extend(timed(run) for run in runs)
        base_wall, base_cpu = (
            statistics.median(t[k] for t in samples["render_scene 1 ray/px (baseline)"]) for k in (0, 1)
        )
        for name, times in samples.items():
            wall, cpu = (statistics.median(t[k] for t in times) for k in (0, 1))
            rows.append(
                {
                    "foliage": foliage,
                    "what": name,
                    "wall_s": wall,
                    "cpu_s": cpu,
                    "max_wall_s": max(t[0] for t in times),
                    "wall_ratio_to_baseline": wall / base_wall,
                    "cpu_ratio_to_baseline": cpu / base_cpu,
                    "samples": len(times),
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    """Print the table (and write --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT (default 1280x720)")
    parser.add_argument("--seeds", type=int, default=3, help="scenes per configuration (default 3)")
    parser.add_argument("--repeats", type=int, default=2, help="passes over every call (default 2)")
    parser.add_argument("--json", type=Path, help="also write the rows, CPU and load as JSON here")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    load_before = os.getloadavg()
    rows = measure(width, height, list(range(args.seeds)), args.repeats)
    load_after = os.getloadavg()
    cpu = cpu_name()
    print(f"{args.size}, {cpu}; load average {load_before[0]:.1f} before, {load_after[0]:.1f} after")
    print(f"{'foliage':<8} {'what':<36} {'wall s':>7} {'max s':>7} {'CPU s':>7} {'wall ×':>7} {'CPU ×':>7}")
    for row in rows:
        print(
            f"{'sparse' if row['foliage'] else 'bare':<8} {row['what']:<36} {row['wall_s']:>7.2f} "
            f"{row['max_wall_s']:>7.2f} {row['cpu_s']:>7.2f} {row['wall_ratio_to_baseline']:>7.2f} "
            f"{row['cpu_ratio_to_baseline']:>7.2f}"
        )
    print("× = median over the median of `render_scene 1 ray/px` (same seeds, same run)")
    frames = [row["wall_s"] for row in rows if str(row["what"]).startswith("flight")]
    print(f"slowest median flight frame {max(frames):.2f} s (budget {BUDGET_S:.1f} s per HD720 frame on 2 cores)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {"size": args.size, "cpu": cpu, "load_average": [load_before[0], load_after[0]], "rows": rows}, indent=1
            )
            + "\n"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
