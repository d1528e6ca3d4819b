"""Shed work instead of falling behind: the onboard loop's work level, from the age of its results.

A result older than `mavlink.max_result_age_s` when published goes out as "no target": on a busy
companion computer (another process holding a core, the tree close and the regions large) the loop
would otherwise send nothing useful, minute after minute. So the daemon watches capture → publish
times and takes a cheaper *level* when they near the limit:

- level 0: every stage as configured;
- level 1: no full-resolution instance step in the roi mode (`roi.full_resolution_instances`), the
  largest single saving on the stereo thread (~50 ms a frame at HD720 on 2 CPU cores);
- level 2: also no per-branch disparity refinement (`stereo.refine_branches`), which grows with the
  branches' pixels near the tree (tens of ms on the geometry thread).

Up: at once when one result is late, or when the median of the last `window_frames` results passes
`raise_at`·limit (the level's effect shows within a few frames, so a window of 5 judges it). Down:
after `calm_frames` results in a row under `lower_at`·limit, one level; a level given back and taken
again within twice that many results was given back too soon, so the next try waits twice as long
(up to 16×): without the back-off the loop would flap between levels every few seconds under a
steady load.
"""

from __future__ import annotations

import statistics
from collections import deque
from dataclasses import dataclass

from branchrange.config.sections import SheddingConfig

#: What each level turns off, for the log, the status line and /health.
LEVEL_ACTIONS: tuple[str, ...] = (
    "none",
    "full-resolution instances off",
    "full-resolution instances and branch refinement off",
)
#: The longest wait before giving a level back, as a multiple of `calm_frames`.
MAX_BACKOFF = 16


@dataclass(frozen=True)
class LevelChange:
    """A change of work level: from, to, and the capture → publish time (s) that decided it."""

    previous: int
    level: int
    age_s: float

    @property
    def raised(self) -> bool:
        return self.level > self.previous


class LoadShedder:
    """Chooses the work level from the ages of published results (see the module docstring).

    `observe` is called from the geometry thread, `level` read by the stereo thread: an int read is
    atomic, and a frame begun at the old level is simply one frame late to change.
    """

    def __init__(self, cfg: SheddingConfig, max_age_s: float):
        self.cfg = cfg
        self.max_age_s = max_age_s
        self.level = 0
        self.changes = 0
        self._recent: deque[float] = deque(maxlen=cfg.window_frames)
        self._calm = 0  # results in a row under lower_at
        self._calm_needed = cfg.calm_frames
        self._since_lowered: int | None = None  # results since the last level given back

    @property
    def actions(self) -> str:
        """What the current level turns off."""
        return LEVEL_ACTIONS[self.level]

    def observe(self, age_s: float) -> LevelChange | None:
        """Take one result's capture → publish time (s); the change of level it causes, if any."""
        if not self.cfg.enabled:
            return None
        self._recent.append(age_s)
        if self._since_lowered is not None:
            self._since_lowered += 1
        limit = self.max_age_s
        late = age_s > limit
        busy = len(self._recent) == self._recent.maxlen and statistics.median(self._recent) > self.cfg.raise_at * limit
        if (late or busy) and self.level < self.cfg.max_level:
            return self._raise(age_s)
        self._calm = self._calm + 1 if age_s < self.cfg.lower_at * limit else 0
        if self._calm >= self._calm_needed and self.level > 0:
            return self._lower(age_s)
        return None

    def _raise(self, age_s: float) -> LevelChange:
        if self._since_lowered is not None and self._since_lowered <= 2 * self._calm_needed:
            self._calm_needed = min(self._calm_needed * 2, MAX_BACKOFF * self.cfg.calm_frames)
        self._since_lowered = None
        return self._set(self.level + 1, age_s)

    def _lower(self, age_s: float) -> LevelChange:
        if self._since_lowered is not None:
            self._calm_needed = self.cfg.calm_frames  # the last give-back held: back to the normal wait
        self._since_lowered = 0
        return self._set(self.level - 1, age_s)

    def _set(self, level: int, age_s: float) -> LevelChange:
        change = LevelChange(self.level, level, age_s)
        self.level = level
        self.changes += 1
        self._recent.clear()  # judge the new level by its own results
        self._calm = 0
        return change

    def state(self) -> dict[str, object]:
        """For /health and /metrics: the level, what it turns off, and how often it changed."""
        return {"enabled": self.cfg.enabled, "level": self.level, "actions": self.actions, "changes": self.changes}
