"""`benchmarks/realtime.py --config FILE` runs a deploy file as the daemon reads it, and renders the flight asked for.

Why: the benchmark's figures stand for what a user gets only if it runs the shipped file as `branchrange
daemon --config` would — same loader, same precedence, only the hardware ties (camera, autopilot link,
log path, API) replaced. `benchmarks/` is not a package: its scripts import their siblings with their own
folder on the path, so the test puts it there first.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from pathlib import Path

import pytest

from branchrange.commands.config_args import config_from_args
from branchrange.config.loader import pipeline_config
from stereo.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import realtime  # noqa: E402

SHIPPED = str(ROOT / "deploy" / "onboard_cpu.toml")


def daemon_config(*argv: str):
    """The configuration `branchrange daemon ARGV` runs with (its own parser and loader, no --source/--mavlink)."""
    args = build_parser("branchrange", "test", ["branchrange.commands.daemon"]).parse_args(["daemon", *argv])
    return config_from_args(args, {"camera.source": None, "mavlink.url": None})


def benchmark_config(mode: str, *argv: str):
    args = realtime.parse_args(list(argv))
    return args, realtime.run_config(realtime.base_config(args), mode, Path("flight"), 14550, Path("r.jsonl"), "")


@pytest.mark.parametrize(
    "extra", [[], ["--set", "cutpoints.target_min_confidence=0.5", "--set", "roi.coarse_width=480"]]
)
def test_the_shipped_file_runs_with_the_daemons_settings(extra: list[str]):
    args, ours = benchmark_config("config", "--config", SHIPPED, *extra)
    theirs = daemon_config("--config", SHIPPED, *extra)
    assert args.modes == ["config", "full-sgbm"]
    assert pipeline_config(ours) == pipeline_config(theirs)  # stereo, roi, cut points, segmenter, masks, tracker
    assert ours.stereo.mode == "roi" and ours.stereo.max_disp == 128 and ours.segmenter.learned.precision == "int8"
    assert ours.mavlink == dataclasses.replace(theirs.mavlink, url="udpout:127.0.0.1:14550")
    assert ours.tracking == theirs.tracking
    assert ours.camera == dataclasses.replace(theirs.camera, source="replay:flight", calibration="")
    assert not ours.api.enabled and ours.log.results_jsonl == "r.jsonl"
    assert ours.branch_tracking == theirs.branch_tracking and ours.masks == theirs.masks


def test_a_named_mode_changes_only_the_stereo_backend_and_mode():
    _, config = benchmark_config("config", "--config", SHIPPED)
    _, baseline = benchmark_config("full-sgbm", "--config", SHIPPED)
    assert baseline == dataclasses.replace(config, stereo=dataclasses.replace(config.stereo, mode="full"))


def test_flags_and_overrides_keep_the_daemons_precedence():
    _, config = benchmark_config("config", "--config", SHIPPED, "--max-disp", "96", "--max-result-age-s", "0.3")
    assert (config.stereo.max_disp, config.mavlink.max_result_age_s) == (96, 0.3)  # the flags over the file
    _, config = benchmark_config("config", "--config", SHIPPED, "--max-disp", "96", "--set", "stereo.max_disp=160")
    assert config.stereo.max_disp == 160  # --set last
    args, config = benchmark_config("roi-sgbm")
    assert config.stereo.max_disp == realtime.UNCONFIGURED_MAX_DISP and args.modes == [
        "full-sgbm",
        "roi-sgbm",
        "roi-emcstereo",
    ]


def test_the_flight_asked_for_is_rendered_in_its_own_folder(capsys: pytest.CaptureFixture[str]):
    assert realtime.flight_path_for(realtime.parse_args([])) == realtime.DEFAULT_SEQUENCE
    fast = realtime.flight_path_for(realtime.parse_args(["--speed", "0.8", "--yaw-rate", "20"]))
    assert fast.name == "flight_hd720_speed0.8_yaw20"
    with pytest.raises(SystemExit):
        realtime.parse_args(["--sequence", "out/flight", "--speed", "0.8"])
    assert "not with --sequence" in capsys.readouterr().err


def test_the_loop_profile_reads_py_spy_stacks_into_stage_and_function_shares():
    import profile_loop  # benchmarks/ is on the path (above)

    raw = (
        "thread (1): MainThread;run (daemon.py:450);stereo_stage (pipeline.py:400);compute (sgbm.py:60) 6\n"
        "thread (2): geometry-send;_geometry_worker (daemon.py:290);estimate_cut_points (cutpoints.py:830) 3\n"
        "thread (2): geometry-send;_geometry_worker (daemon.py:291);estimate_cut_points (cutpoints.py:840);"
        "fit (cylinder_section.py:20) 1\n"
        "thread (1): MainThread;run_mode (realtime.py:200);DecodedFrames.__init__ (preloaded.py:30);"
        "read_rgb (image_files.py:50) 10\n"
        "not a stack line\n"
    )
    stacks = profile_loop.parse_raw(raw)
    assert [(thread, count) for thread, _, count in stacks] == [
        ("MainThread", 6),
        ("geometry-send", 3),
        ("geometry-send", 1),
        ("MainThread", 10),
    ]
    table = profile_loop.profile_table(stacks, top=10)
    assert table["samples"] == 20 and table["loop_samples"] == 10
    assert {r["name"]: r["share"] for r in table["stages"]} == {
        "frames decoded ahead (before the clock)": 0.5,
        "stereo (daemon main thread)": 0.3,
        "geometry + send": 0.2,
    }  # the functions' shares are of the 10 samples that are not the decoding ahead
    own = {r["name"]: r["share"] for r in table["self"]}
    assert own == {
        "compute (sgbm.py)": 0.6,
        "estimate_cut_points (cutpoints.py)": 0.3,
        "fit (cylinder_section.py)": 0.1,
    }
    inclusive = {r["name"]: r["share"] for r in table["total"]}
    assert inclusive["estimate_cut_points (cutpoints.py)"] == 0.4  # two lines of one function: counted once a stack
    assert inclusive["_geometry_worker (daemon.py)"] == 0.4 and inclusive["run (daemon.py)"] == 0.6


def test_the_loop_profile_counts_the_stereo_workers_and_leaves_their_start_up_out():
    """`--subprocesses` stacks start with the processes: a child's main thread is a stereo worker, its loop the
    stereo and cut-point stage, its imports and pipeline building before the clock."""
    import profile_loop

    run, worker = 'process 10:"python realtime.py"', 'process 11:"python -c import spawn_main; spawn_main(fd=4)"'
    raw = (
        f"{run};thread (1): MainThread;run (daemon.py:450);submit (stereo_workers.py:190) 1\n"
        f"{run};{worker};thread (7): MainThread;_serve (stereo_workers.py:320);compute (sgbm.py:60) 6\n"
        f"{run};{worker};thread (7): MainThread;_serve (stereo_workers.py:315);pipeline_for (frame_results.py:9) 2\n"
        f"{run};{worker};thread (7): MainThread;spawn_main (spawn.py:120);<module> (torch/__init__.py:1) 1\n"
        f"{run};thread (2): geometry-send;_geometry_worker (daemon.py:290);finish_frame (pipeline.py:730) 3\n"
    )
    stacks = profile_loop.parse_raw(raw)
    assert [thread for thread, _, _ in stacks] == [
        "MainThread",
        "stereo-worker",
        "stereo-worker",
        "stereo-worker",
        "geometry-send",
    ]
    table = profile_loop.profile_table(stacks, top=10)
    assert table["samples"] == 13 and table["loop_samples"] == 10
    stages = {r["name"]: r["samples"] for r in table["stages"]}
    assert stages == {
        "stereo + cut points (worker processes)": 6,
        "geometry + send": 3,
        "workers' start-up (before the clock)": 3,
        "stereo (daemon main thread)": 1,
    }
    assert {r["name"] for r in table["self"]} == {
        "compute (sgbm.py)",
        "finish_frame (pipeline.py)",
        "submit (stereo_workers.py)",
    }


def test_a_child_processs_cpu_and_parent_are_read_from_proc():
    """`realtime.child_cpu_s` (the workers' CPU at the clock's start) and `soak.child_pids` (the daemon's workers
    counted with it) on a real child that burns CPU: found as this process's child, with CPU time that grows."""
    import subprocess

    import soak

    if not Path("/proc/self/stat").exists():
        pytest.skip("needs Linux's /proc")
    child = subprocess.Popen(
        [sys.executable, "-c", "import time\nend = time.time() + 30\nwhile time.time() < end: pass"]
    )
    try:
        time.sleep(0.5)
        first = realtime.child_cpu_s(child.pid)
        assert child.pid in soak.child_pids(os.getpid())
        time.sleep(0.5)
        assert realtime.child_cpu_s(child.pid) > first > 0
    finally:
        child.kill()
        child.wait()
    assert realtime.child_cpu_s(child.pid) == 0.0 and child.pid not in soak.child_pids(os.getpid())  # gone
