"""`train-segmenter` on the randomized domain, and a run killed mid-way and resumed.

Why: training at scale renders thousands of randomized scenes once and runs unattended for hours; a cache that
mixed the randomized scenes with the generator's would train on the wrong data without a word, and a resume that
missed one piece of state (the optimiser's moments, the schedule, the crop generator) would end on other weights
than the recipe promises. The run here is tiny (width 4, crops of 64 px, 6 steps) on three randomized scenes; the
kill is a real SIGKILL of the training process right after its checkpoint at step 4.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from itertools import chain
from pathlib import Path

import numpy as np
import pytest
import torch

from branchrange.cli import main
from branchrange.commands.train_segmenter import training_config
from branchrange.learning.resume import CHECKPOINT_NAME
from branchrange.learning.samples import (
    DOMAINS,
    cached_randomized_sample,
    randomized_sample_path,
    render_randomized_sample,
    render_samples,
    sample_path,
)
from branchrange.learning.training import TRAINING_DOMAINS, train_branchnet
from stereo.synth.randomized import RandomizedSwitches

ROOT = Path(__file__).resolve().parents[1]
#: a tiny run on randomized scenes 1–2 (validation: 3), a validation and checkpoint every 2 steps
SETTINGS = [
    'domain="randomized"',
    "train_seeds=[1, 3]",
    "val_seeds=[3, 4]",
    "steps=6",
    "batch=2",
    "crop=64",
    "width=4",
    "threads=1",
    "val_every=2",
]
#: the training process kills itself right after logging this validation (its checkpoint is written before)
KILLED_AT_STEP = 4
KILLED_RUN = textwrap.dedent(
    f"""
    import os, signal, sys
    from pathlib import Path
    from branchrange.commands.train_segmenter import training_config
    from branchrange.learning.training import TRAINING_DOMAINS, train_branchnet

    def log(line):
        if line.startswith("step {KILLED_AT_STEP} "):
            os.kill(os.getpid(), signal.SIGKILL)

    train_branchnet(training_config(None, sys.argv[3:]), Path(sys.argv[1]), Path(sys.argv[2]), log=log)
    """
)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    """A cache holding the three randomized scenes of `SETTINGS`, rendered once for the module in two processes
    (the pool's path; ~2 s a scene)."""
    data = tmp_path_factory.mktemp("data")
    assert render_samples(data, [(1, False), (2, False), (3, False)], workers=2, domain="randomized") == 3
    return data


def test_the_randomized_cache_is_keyed_by_seed_size_and_switches_and_holds_the_rendered_sample(scenes, tmp_path):
    path = randomized_sample_path(scenes, 2)
    assert path.is_file() and not sample_path(scenes, 2).exists()  # never under a generator scene's name
    held = RandomizedSwitches.only("bark")
    names = {
        path.name,
        randomized_sample_path(scenes, 2, switches=held).name,
        randomized_sample_path(scenes, 2, size=(320, 180)).name,
        randomized_sample_path(scenes, 3).name,
    }
    assert len(names) == 4
    assert randomized_sample_path(scenes, 2, switches=RandomizedSwitches()) == path  # None: the default switches
    small = cached_randomized_sample(tmp_path, 7, size=(160, 96), switches=held)
    rendered = render_randomized_sample(7, (160, 96), held)
    assert small["left"].shape == (96, 160, 3)
    assert all(np.array_equal(small[key], rendered[key]) for key in rendered)
    assert [p.name for p in tmp_path.iterdir()] == [randomized_sample_path(tmp_path, 7, (160, 96), held).name]


def test_a_run_killed_and_resumed_ends_with_the_weights_of_one_that_was_not(scenes, tmp_path, capsys):
    config = training_config(None, SETTINGS)
    whole = train_branchnet(config, tmp_path / "whole", scenes, log=lambda _: None)
    assert whole["config"]["domain"] == "randomized"
    assert sorted(p.name for p in scenes.iterdir() if p.name.startswith("sample_")) == []  # no generator scene

    killed = tmp_path / "killed"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run(
        [sys.executable, "-c", KILLED_RUN, str(killed), str(scenes), *SETTINGS],
        env=env,
        capture_output=True,
        timeout=300,
    )
    assert run.returncode == -signal.SIGKILL, run.stderr.decode()[-2000:]
    assert (killed / CHECKPOINT_NAME).is_file() and not (killed / "branchnet.onnx").exists()

    argv = ["train-segmenter", "--out", str(killed), "--data", str(scenes), "--no-calibrate", "--resume"]
    assert main([*argv, *(a for s in SETTINGS for a in ("--set", s))]) == 0
    assert f"resumed from {killed / CHECKPOINT_NAME} after step {KILLED_AT_STEP}" in capsys.readouterr().out
    reference, resumed = (torch.load(d / "branchnet.pt", weights_only=True) for d in (tmp_path / "whole", killed))
    assert all(torch.equal(reference[k], resumed[k]) for k in reference)
    meta = json.loads((killed / "branchnet.json").read_text())
    assert meta["onnx_sha256"] == whole["onnx_sha256"]
    assert [row["step"] for row in [meta["final"]]] == [6]
    assert (killed / "metrics.csv").read_text().count("\n") == 1 + 3  # header + the validations at 2, 4, 6


def test_resume_refuses_a_missing_checkpoint_and_one_of_other_settings(scenes, tmp_path, capsys):
    argv = ["train-segmenter", "--out", str(tmp_path / "run"), "--data", str(scenes), "--no-calibrate", "--resume"]
    settings = [a for s in SETTINGS for a in ("--set", s)]
    assert main([*argv, *settings]) == 2
    assert "resume: no checkpoint" in capsys.readouterr().err
    train_branchnet(training_config(None, SETTINGS), tmp_path / "run", scenes, log=lambda _: None)
    assert main([*argv, *settings, "--set", "lr=0.01"]) == 2
    err = capsys.readouterr().err
    assert "saved by a run with other settings (lr)" in err and "Traceback" not in err
    assert main([*argv[:-2], "--calibrate-only", "--resume"]) == 2
    assert "--resume continues a training run" in capsys.readouterr().err


def test_the_randomized_domain_is_a_checked_setting() -> None:
    with pytest.raises(ValueError, match="domain must be one of generator, randomized, mixed"):
        training_config(None, ['domain="real"'])
    with pytest.raises(ValueError, match="hardware_seeds are generator scenes"):
        training_config(None, ['domain="randomized"', "hardware_seeds=[5, 7]"])
    assert training_config(None, []).domain == "generator"  # the default is unchanged


def test_the_mixed_domain_trains_and_validates_on_both_domains_scenes(scenes, tmp_path):
    data = shutil.copytree(scenes, tmp_path / "data")  # the module's cache keeps randomized scenes only
    config = training_config(None, ['domain="mixed"', *(s for s in SETTINGS if not s.startswith("domain"))])
    log: list[str] = []
    meta = train_branchnet(config, tmp_path / "run", data, log.append)
    assert meta["config"]["domain"] == "mixed"
    assert "rendered 3 generator scenes" in log[0] and not any("randomized scenes" in line for line in log)
    for seed in (1, 2, 3):  # training seeds 1–2 and validation seed 3, of each domain
        assert sample_path(data, seed).is_file() and randomized_sample_path(data, seed).is_file()
    log.clear()
    train_branchnet(config, tmp_path / "again", data, log.append)
    assert not any(line.startswith("rendered") for line in log)  # both caches already full
    assert set(chain.from_iterable(TRAINING_DOMAINS.values())) == set(DOMAINS)
