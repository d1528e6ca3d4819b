"""The daemon's work level: up at once when results near the age limit, down when calm, with a back-off."""

from __future__ import annotations

import numpy as np

from branchrange.config.sections import SheddingConfig
from branchrange.onboard.load_shedding import LoadShedder

LIMIT_S = 0.5


def feed(shedder: LoadShedder, ages_s) -> list[int]:
    """The level after each age (s)."""
    levels = []
    for age in ages_s:
        shedder.observe(age)
        levels.append(shedder.level)
    return levels


def test_a_late_result_raises_the_level_at_once_and_calm_gives_it_back():
    shedder = LoadShedder(SheddingConfig(calm_frames=10), LIMIT_S)
    assert feed(shedder, [0.1] * 20) == [0] * 20  # calm at level 0: nothing to give back
    assert feed(shedder, [0.6]) == [1]  # late: one level up at once
    assert feed(shedder, [0.6]) == [2]
    assert feed(shedder, [0.6]) == [2]  # max_level
    levels = feed(shedder, [0.1] * 20)  # calm (under lower_at · limit = 0.2 s) for 10 results: one level back
    assert levels[8] == 2 and levels[9] == 1 and levels[19] == 0
    assert shedder.changes == 4


def test_a_busy_median_raises_but_a_single_slow_frame_under_the_limit_does_not():
    shedder = LoadShedder(SheddingConfig(window_frames=5), LIMIT_S)
    assert feed(shedder, [0.1, 0.1, 0.45, 0.1, 0.1]) == [0] * 5  # one slow frame, still in time
    assert feed(shedder, [0.4, 0.4]) == [0, 1]  # now the median of the last 5 passes 0.7 · 0.5 s


def test_in_between_ages_hold_the_level():
    shedder = LoadShedder(SheddingConfig(calm_frames=5), LIMIT_S)
    feed(shedder, [0.6])
    assert feed(shedder, [0.3] * 50) == [1] * 50  # above lower_at, below raise_at: no reason to change


def test_a_level_given_back_too_soon_waits_twice_as_long_next_time():
    shedder = LoadShedder(SheddingConfig(calm_frames=10), LIMIT_S)
    feed(shedder, [0.6])  # level 1
    assert feed(shedder, [0.1] * 10)[-1] == 0  # given back after 10 calm results
    feed(shedder, [0.6])  # and needed again at once: that give-back was too soon
    levels = feed(shedder, [0.1] * 20)
    assert levels[9] == 1 and levels[19] == 0  # now 20 calm results are needed
    feed(shedder, [0.1] * 40)
    feed(shedder, [0.6])  # a long time later: the wait stays doubled only until a give-back holds
    assert feed(shedder, [0.1] * 20)[-1] == 0


def test_off_means_off():
    shedder = LoadShedder(SheddingConfig(enabled=False), LIMIT_S)
    assert feed(shedder, np.full(10, 2.0)) == [0] * 10
    assert shedder.state() == {"enabled": False, "level": 0, "actions": "none", "changes": 0}
