"""A wall-clock jump of an hour either way (GPS time arriving, an operator setting the clock) changes no
freshness decision: the relay sends a fresh result as a target and an old one as "no target" by the
monotonic clock alone (issue 39). The jump is real for the process under test (libfaketime preloaded,
`wall_clock_shim`), the machine's clock is left alone."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from wall_clock_shim import shim_env

HERE = Path(__file__).resolve().parent


def test_a_wall_clock_jump_changes_no_freshness_decision(tmp_path):
    env = {**os.environ, **shim_env(tmp_path / "offset"), "PYTHONPATH": str(HERE)}
    done = subprocess.run(
        [sys.executable, str(HERE / "clock_jump_case.py"), str(tmp_path / "offset")],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    case = json.loads(done.stdout.strip().splitlines()[-1])
    limit = case["max_result_age_s"]
    for phase in case["phases"]:
        # the shim is in force: the wall clock moved by the jump, the monotonic one did not
        assert abs(phase["wall_moved_s"] - phase["jump_s"]) < 5, phase["wall_moved_s"]
        targets = [at for at, is_target in phase["sets"] if is_target]
        no_targets = [at for at, is_target in phase["sets"] if not is_target]
        # fresh stays fresh: a target right after the publish, whichever way the clock jumped ...
        assert targets and min(targets) < limit / 2, phase
        # ... and goes stale on time: none after the limit (a few ms for the loopback), "no target" after it
        assert max(targets) <= limit + 0.05, phase
        assert any(at > limit + 0.1 for at in no_targets), phase
