"""Where the onboard loop's CPU goes: the shipped configuration's real-time run (`benchmarks/realtime.py`, frames
released at their timestamps through the daemon's own threads) sampled by py-spy, per stage and per function.
The frames are decoded into memory before the clock starts, as realtime.py does by default, so a replay's PNG
decoding (a quarter of the samples on 2 cores) is not counted as the loop's; `--decode-on-the-fly` counts it.

py-spy (`pip install py-spy`) samples every thread of the run and of its child processes `--rate` times a second
without stopping it, idle threads left out. The table reads its raw stacks: each sample's thread is its stage —
with `stereo.workers` other than 1 (as shipped) the worker processes' main threads are the stereo stage and the
cut points (`Pipeline.stereo_stage`, `Pipeline.cut_point_stage`) and the daemon's main thread only dispatches;
with one worker the daemon's main thread is the stereo stage (coarse pass, segmenter, regions); `geometry-send`
the geometry stage (with workers only its end, `Pipeline.finish_frame`: tracking, target) and the send,
`latest-frame-capture` the camera, `mavlink-relay` the link. What happens before the clock starts is a stage of its
own each: the frames' decoding ahead, and the workers' start-up (imports, their pipeline built; their one warm-up
frame counts as the loop's). Each function's share is of the samples that are not before the clock: its own (`self`:
the function was running, native code it called included) and inclusive (`total`: anywhere on the stack). The flame
graph (SVG) is py-spy's own, from a second run of the same command.

    .venv/bin/branchrange synth-flight --out out/bench/flight_hd720_150 --seed 1 --frames 150 --start-m 3 --end-m 0.8
    .venv/bin/python benchmarks/profile_loop.py --sequence out/bench/flight_hd720_150 \\
        --json benchmarks/results/profile_loop.json --flamegraph benchmarks/results/profile_loop.svg
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

from machine import cpu_name  # a script's own folder is on its import path

BENCHMARKS = Path(__file__).resolve().parent
#: the function (as py-spy names it) that decodes the replay's frames into memory before the clock starts
DECODING_AHEAD = "DecodedFrames.__init__ "
#: a stereo worker's loop (`stereo_workers._serve`), and what it runs before its first frame counts
WORKER_LOOP, WORKER_SET_UP = "_serve (", "pipeline_for ("
#: the name `parse_raw` gives the main thread of a child process of the run (a stereo worker)
WORKER_THREAD = "stereo-worker"
#: stages of the samples before the clock starts, left out of the functions' shares
DECODED_AHEAD_STAGE, WORKER_START_STAGE = (
    "frames decoded ahead (before the clock)",
    "workers' start-up (before the clock)",
)
#: a process at the head of a `--subprocesses` stack: `process PID:"command line";`
PROCESS = re.compile(r'process \d+:".*?";')
#: a sampled thread's name → the loop's stage it runs
STAGES = {
    WORKER_THREAD: "stereo + cut points (worker processes)",
    "MainThread": "stereo (daemon main thread)",
    "geometry-send": "geometry + send",
    "latest-frame-capture": "camera capture",
    "mavlink-relay": "MAVLink relay",
}


def parse_raw(text: str) -> list[tuple[str, list[str], int]]:
    """py-spy's raw (collapsed) stacks with thread names (`record -t -f raw`, `--subprocesses`: each stack then
    starts with its process and the processes above it, `process PID:"command"`): (thread name, frames root
    first, samples) per line; a frame is `function (file:line)`. A child process's main thread is named
    `WORKER_THREAD` (the run's only children are its stereo workers)."""
    stacks = []
    for line in text.splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        processes = 0
        while (process := PROCESS.match(stack)) is not None:  # its command line may hold ";" itself
            processes, stack = processes + 1, stack[process.end() :]
        if not stack:
            continue
        thread, *frames = stack.split(";")
        name = thread.partition(": ")[2] or thread
        if processes > 1 and name == "MainThread":
            name = WORKER_THREAD
        stacks.append((name, frames, int(count)))
    return stacks


def before_the_clock(thread: str, frames: list[str]) -> str | None:
    """The stage of a sample taken before the run's clock starts, None for the loop's own."""
    if any(frame.startswith(DECODING_AHEAD) for frame in frames):
        return DECODED_AHEAD_STAGE
    if thread == WORKER_THREAD and (
        not any(frame.startswith(WORKER_LOOP) for frame in frames)
        or any(frame.startswith(WORKER_SET_UP) for frame in frames)
    ):
        return WORKER_START_STAGE
    return None


def function_of(frame: str) -> str:
    """`estimate_cut_points (branchrange/core/cutpoints.py:830)` → `estimate_cut_points (cutpoints.py)`: a function
    counted once whatever line of it was sampled."""
    name, _, where = frame.partition(" (")
    path = where.rstrip(")").rpartition(":")[0]
    return f"{name} ({Path(path).name})" if path else name


def profile_table(stacks: list[tuple[str, list[str], int]], top: int) -> dict:
    """Shares of all samples per stage, and per function (self and inclusive, the `top` functions by each) of
    the samples that are not before the clock (`before_the_clock`: the frames' decoding ahead, the workers'
    start-up): that work is the replay's and the start's, not the loop's, and would otherwise top the table."""
    total = sum(count for _, _, count in stacks) or 1
    stages: Counter[str] = Counter()
    own: Counter[str] = Counter()
    inclusive: Counter[str] = Counter()
    for thread, frames, count in stacks:
        early = before_the_clock(thread, frames)
        if early is not None:
            stages[early] += count
            continue
        stages[STAGES.get(thread, "other")] += count
        if frames:
            own[function_of(frames[-1])] += count
        for function in {function_of(frame) for frame in frames}:
            inclusive[function] += count

    loop = total - stages[DECODED_AHEAD_STAGE] - stages[WORKER_START_STAGE] or 1

    def shares(counter: Counter[str], n: int | None = None, of: int = total) -> list[dict]:
        return [{"name": k, "share": v / of, "samples": v} for k, v in counter.most_common(n)]

    return {
        "samples": total,
        "loop_samples": loop,
        "stages": shares(stages),
        "self": shares(own, top, loop),
        "total": shares(inclusive, top, loop),
    }


def run_py_spy(py_spy: str, fmt: str, out: Path, rate: int, command: list[str]) -> None:
    """`py-spy record` of `command` and its child processes (thread names on, idle threads off) into `out` in `fmt`."""
    subprocess.run(
        [py_spy, "record", "-t", "--subprocesses", "-r", str(rate), "-f", fmt, "-o", str(out), "--", *command],
        check=True,
        stdout=subprocess.DEVNULL,
    )


def print_table(table: dict, cpu: str) -> None:
    print(f"{table['samples']} samples — {cpu}")
    print(f"{'stage':<32} {'share':>7}")
    for row in table["stages"]:
        print(f"{row['name']:<32} {row['share']:>7.1%}")
    print(f"\nfunctions: shares of the {table['loop_samples']} samples after the clock started")
    for kind in ("self", "total"):
        print(f"\n{'function (' + kind + ')':<72} {'share':>7}")
        for row in table[kind]:
            print(f"{row['name'][:72]:<72} {row['share']:>7.1%}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, required=True, help="a `branchrange synth-flight` recording")
    parser.add_argument("--config", type=Path, default=Path("deploy/onboard_cpu.toml"), help="the deploy file")
    parser.add_argument("--segmenter", default="builtin", choices=("builtin", "truth"), help="as realtime.py's")
    parser.add_argument(
        "--decode-on-the-fly",
        action="store_true",
        help="realtime.py's flag: decode each frame at its release (default: all decoded into memory first)",
    )
    parser.add_argument("--rate", type=int, default=100, help="samples a second (default 100)")
    parser.add_argument("--top", type=int, default=25, help="functions listed (default 25)")
    parser.add_argument("--json", type=Path, help="write the table here")
    parser.add_argument("--flamegraph", type=Path, help="also write py-spy's flame graph (SVG) of a second run here")
    args = parser.parse_args(argv)
    py_spy = shutil.which("py-spy") or shutil.which("py-spy", path=str(Path(sys.executable).parent))
    if py_spy is None:
        print("py-spy is not installed: pip install py-spy", file=sys.stderr)
        return 2
    if not args.sequence.is_dir():
        print(f"--sequence {args.sequence}: no such recording (branchrange synth-flight --out DIR writes one)")
        return 2
    with tempfile.TemporaryDirectory() as folder:
        command = [
            sys.executable,
            str(BENCHMARKS / "realtime.py"),
            "--config",
            str(args.config),
            "--sequence",
            str(args.sequence),
            "--segmenter",
            args.segmenter,
            "--modes",
            "config",
            "--json",
            str(Path(folder) / "realtime.json"),
            *(["--decode-on-the-fly"] if args.decode_on_the_fly else []),
        ]
        raw = Path(folder) / "profile.raw"
        run_py_spy(py_spy, "raw", raw, args.rate, command)
        table = profile_table(parse_raw(raw.read_text(encoding="utf-8")), args.top)
        realtime = json.loads((Path(folder) / "realtime.json").read_text(encoding="utf-8"))
        if args.flamegraph:
            args.flamegraph.parent.mkdir(parents=True, exist_ok=True)
            run_py_spy(py_spy, "flamegraph", args.flamegraph, args.rate, command)
    cpu = cpu_name()
    print_table(table, cpu)
    run = next(iter(realtime["modes"].values()))
    print(
        f"\nthe profiled run: {run['fresh_rate_hz']:.2f} fresh Hz, capture → send p95 {run['latency_ms']['p95']:.0f} ms"
    )
    if args.json:
        report = {
            "cpu": cpu,
            "config": str(args.config),
            "sequence": str(args.sequence),
            "segmenter": args.segmenter,
            "rate": args.rate,
            "preloaded": not args.decode_on_the_fly,
            "run": {"fresh_rate_hz": run["fresh_rate_hz"], "latency_ms": run["latency_ms"]},
            **table,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
