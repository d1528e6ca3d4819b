"""Randomized scenes on disk: one compressed `.npz` and one plan `.json` per scene, and a contact sheet."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from stereo.synth.camera import SynthCamera
from stereo.synth.preview import contact_sheet
from stereo.synth.randomized import RandomizedSample, RandomizedSwitches, plan_summary, render_randomized


def write_randomized(
    folder: Path, seeds: Sequence[int], camera: SynthCamera, switches: RandomizedSwitches, supersample: int
) -> list[RandomizedSample]:
    """Render `seeds` and write `randomized_<seed>.npz` (left, right, disparity = SGBM after dropout,
    exact_disparity, instances; see `RandomizedSample`) and `randomized_<seed>.json` (the factors drawn)
    under `folder` (made if needed); returns the samples. Raises OSError when the folder cannot be written."""
    folder.mkdir(parents=True, exist_ok=True)
    samples = []
    for seed in seeds:
        sample = render_randomized(seed, camera, switches, supersample)
        arrays = {
            name: getattr(sample, name) for name in ("left", "right", "disparity", "exact_disparity", "instances")
        }
        np.savez_compressed(folder / f"randomized_{seed}.npz", **arrays)
        plan = {**plan_summary(sample.plan), "camera": camera.to_dict()}
        (folder / f"randomized_{seed}.json").write_text(json.dumps(plan, indent=1) + "\n")
        samples.append(sample)
    return samples


def randomized_contact_sheet(samples: Sequence[RandomizedSample], columns: int = 3) -> np.ndarray:
    """RGB picture of `samples`: each left image beside its instance mask, `columns` a row."""
    return contact_sheet([s.left for s in samples], [s.instances for s in samples], columns)
