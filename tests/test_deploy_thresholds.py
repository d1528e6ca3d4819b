"""The shipped deploy files agree with the shipped model: every threshold that the model's confidence
calibration measured (`confidence_calibrations` in its JSON) is the value measured at the file's own setting
— the model and precision, the width the network sees and its trunk band, normal light — or its line's
comment names the calibrated value it departs from, and why.

Why: `deploy/onboard.toml` kept `mavlink.obstacle_min_confidence = 0.3` after the model's calibration
moved to 0.16, so real branches between the two were left out of the avoidance fence (issue 49).
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from branchrange.config.check import key_lines
from branchrange.config.loader import Config, config_from_dict
from branchrange.core.segmentation.learned import SHIPPED_MODELS

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
#: dotted key of a deploy file → the column of the calibration table it must agree with
CALIBRATED = {
    "cutpoints.target_min_confidence": "target_min_confidence",
    "mavlink.obstacle_min_confidence": "obstacle_min_confidence",
}
#: a number in a comment (`0.16`, `.16`)
NUMBER = re.compile(r"(?<![\d.])\d*\.\d+|(?<![\d.])\d+(?![\d.])")


def shipped_calibration(cfg: Config) -> dict[str, Any] | None:
    """The shipped model's calibration table that the run of `cfg` reads its confidences through in normal
    light, None when the run uses no shipped, calibrated learned model (its thresholds are its own)."""
    learned = cfg.segmenter.learned
    if cfg.segmenter.model != "learned" or learned.model or not learned.calibrated:
        return None
    width = learned.network_width or (cfg.roi.coarse_width if cfg.stereo.mode == "roi" else 0)
    assert width, "stereo.mode = 'full' with network_width = 0: the width the network sees is the camera's; set it"
    meta = json.loads(SHIPPED_MODELS[learned.precision].with_suffix(".json").read_text(encoding="utf-8"))
    setting = (width, learned.trunk_band_px, "normal")
    found = [
        table
        for table in meta["confidence_calibrations"]
        if (table["network_width"], table.get("trunk_band_px", 0), table.get("light", "normal")) == setting
    ]
    assert len(found) == 1, f"the shipped {learned.precision} model has no calibration measured at {setting}"
    return found[0]


def _setting(cfg: Config, key: str) -> Any:
    """The value of dotted `key` in `cfg`."""
    section, name = key.split(".")
    return getattr(getattr(cfg, section), name)


def disagreements(text: str) -> list[str]:
    """Each calibrated threshold of the TOML `text` that differs from the shipped calibration without a
    comment on its line naming the calibrated value (a default that differs: the file must set it)."""
    cfg = config_from_dict(tomllib.loads(text))
    table = shipped_calibration(cfg)
    if table is None:
        return []
    lines = key_lines(text)
    source = text.splitlines()
    found = []
    for key, column in CALIBRATED.items():
        if key == "mavlink.obstacle_min_confidence" and not cfg.mavlink.enabled:
            continue  # no avoidance fence is sent
        value, measured = _setting(cfg, key), table[column]
        if measured is None or value == measured:
            continue
        if key not in lines:
            found.append(f"{key}: the default {value} differs from the calibration's {measured}: set it")
            continue
        comment = source[lines[key] - 1].partition("#")[2]
        if not any(float(number) == measured for number in NUMBER.findall(comment)):
            found.append(
                f"line {lines[key]}: {key} = {value} differs from the calibration's {measured}; "
                f"a comment on its line naming {measured} must say why"
            )
    return found


@pytest.mark.parametrize("path", sorted(DEPLOY.glob("*.toml")), ids=lambda p: p.name)
def test_each_shipped_threshold_agrees_with_the_shipped_calibration(path):
    assert disagreements(path.read_text(encoding="utf-8")) == []


def onboard_with_obstacle_line(line: str) -> str:
    """deploy/onboard.toml with its `obstacle_min_confidence` line replaced by `line` ('' : left out)."""
    text = (DEPLOY / "onboard.toml").read_text(encoding="utf-8")
    edited = re.sub(r"^obstacle_min_confidence = .*\n", line + "\n" if line else "", text, flags=re.MULTILINE)
    assert edited != text
    return edited


def test_a_threshold_left_behind_by_the_calibration_is_found():
    """The onboard file as it was before issue 49: 0.3 where the calibration says 0.16."""
    stale = onboard_with_obstacle_line("obstacle_min_confidence = 0.3    # less confident cut points are not fenced")
    (problem,) = disagreements(stale)
    assert "mavlink.obstacle_min_confidence = 0.3 differs from the calibration's 0.16" in problem


def test_a_departure_with_its_reason_passes_and_a_default_that_differs_does_not():
    reasoned = onboard_with_obstacle_line(
        "obstacle_min_confidence = 0.2   # above the calibration's 0.16: this orchard's twigs are fenced off anyway"
    )
    assert disagreements(reasoned) == []
    (problem,) = disagreements(
        onboard_with_obstacle_line("")
    )  # the default (0.18) is the trunk band's value, not one look's
    assert problem.startswith("mavlink.obstacle_min_confidence: the default 0.18 differs from the calibration's 0.16")
