"""Detect slowly, track at camera rate: when the roi mode runs its segmenter, and when it carries masks over.

With `[roi] keyframe_interval_s` > 0 the segmenter (its network look and instance steps, ~150 ms a frame
at HD720 on 2 CPU cores) runs on *keyframes* only; the frames between reuse the last frame's instances,
each branch moved to where its pixels went (`branch_propagation.propagate_labels`), and run the coarse
pass, the region stereo, the branch refinement and the cut points as usual. A keyframe comes
- on the first frame, and after `reset` (a new sequence, a reopened camera);
- `keyframe_interval_s` after the last one (new branches appear within that, plus one frame);
- at once after a frame that lost a branch: its image match failed (`track_min_ncc`), the new disparity
  did not support where it was carried (`track_min_support`), or its cut point jumped from the last
  frame's (`track_max_jump_m`, checked in the geometry half) — a branch is never measured at a guessed place;
- when the last frame had no branch left to carry.
Masks given with the frame (a recording's, the API's) are always used as they are: nothing to track.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from branchrange.core.masks import BranchMasks

Origin = Literal["keyframe", "tracked"]

#: With a keyframe worker, a keyframe is also wanted once the view moved this share of the frame's width
#: (or height) since the last one: what entered at the edge is covered by no track.
NEW_VIEW_SHARE = 0.08


@dataclass(frozen=True)
class CarriedFrame:
    """What the next frame may carry over: the anchor it is matched on — the keyframe's rectified left image
    in grey (`uint8 H×W`) and its final instances (less the branches lost since) —, where the last frame
    found each branch and the trunk (id → (du, dv) px from the anchor, `branch_propagation.Propagation`;
    empty after a keyframe), each branch's own disparity range in the last frame (id → [low, high) px,
    `roi.branch_gates`), and the keyframe's capture time (ns)."""

    grey: np.ndarray
    masks: BranchMasks
    gates: dict[int, tuple[float, float]]
    keyframe_ns: int
    offsets: dict[int, tuple[float, float]] = field(default_factory=dict)


def grey_of(left: np.ndarray) -> np.ndarray:
    """The `uint8 H×W` grey of a rectified RGB `uint8 H×W×3` image."""
    return cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)


class KeyframeSchedule:
    """Decides per frame whether a keyframe is wanted, and keeps what a tracked frame needs."""

    def __init__(self) -> None:
        self._carried: CarriedFrame | None = None
        self._keyframe_due = True
        self._requested = False  # set by the geometry half (another thread), taken by `carry_from` / `submitted`

    def request(self) -> None:
        """Ask for a keyframe next (the geometry half found a carried branch's cut point untrustworthy)."""
        self._requested = True

    def carry_from(self, timestamp_ns: int, interval_s: float) -> CarriedFrame | None:
        """What the frame captured at `timestamp_ns` (ns) may carry over, keyframes `interval_s` (s) apart;
        None when it must be a keyframe (the keyframe runs on this frame: no worker)."""
        requested, self._requested = self._requested, False
        if self._due(timestamp_ns, interval_s, requested):
            return None
        return self._carried

    def due(self, timestamp_ns: int, interval_s: float) -> bool:
        """With a keyframe worker: whether a keyframe is wanted at the frame captured at `timestamp_ns` (ns) —
        on schedule, after a loss or a request, when nothing is carried, or when the view has moved on by
        `NEW_VIEW_SHARE` of the frame since the keyframe (what entered is covered by no track). Stays wanted
        until `submitted`."""
        return self._due(timestamp_ns, interval_s, self._requested) or self._view_moved()

    def submitted(self) -> None:
        """A keyframe was handed to the worker: the loss or request that asked for it is answered."""
        self._keyframe_due = self._requested = False

    def anchor(self, timestamp_ns: int, max_age_s: float) -> CarriedFrame | None:
        """With a keyframe worker: what the frame captured at `timestamp_ns` (ns) tracks from, whatever the
        schedule — None when nothing is carried, no branch is left, or the keyframe is `max_age_s` (s) old."""
        carried = self._carried
        if carried is None or not carried.masks.branch_ids():
            return None
        if not 0 <= timestamp_ns - carried.keyframe_ns < max_age_s * 1e9:
            return None
        return carried

    def adopt(
        self,
        grey: np.ndarray,
        masks: BranchMasks,
        gates: dict[int, tuple[float, float]],
        keyframe_ns: int,
        shift: tuple[float, float],
    ) -> None:
        """Take a keyframe the worker finished (on the frame captured at `keyframe_ns`, older than the frame now):
        the next frame tracks from it, every branch and the trunk searched first at `shift` (px, the image's
        motion since that frame)."""
        ids = [*masks.branch_ids(), *([] if masks.trunk_id is None else [masks.trunk_id])]
        self._carried = CarriedFrame(grey, masks, gates, keyframe_ns, {i: shift for i in ids})

    def _due(self, timestamp_ns: int, interval_s: float, requested: bool) -> bool:
        carried = self._carried
        if carried is None or self._keyframe_due or requested or not carried.masks.branch_ids():
            return True
        return not 0 <= timestamp_ns - carried.keyframe_ns < interval_s * 1e9

    def _view_moved(self) -> bool:
        """The carried branches and trunk moved, by their median, more than `NEW_VIEW_SHARE` of the frame."""
        carried = self._carried
        if carried is None or not carried.offsets:
            return False
        du, dv = (float(np.median(axis)) for axis in zip(*carried.offsets.values()))
        height, width = (int(n) for n in carried.grey.shape)
        return abs(du) > NEW_VIEW_SHARE * width or abs(dv) > NEW_VIEW_SHARE * height

    def done(
        self,
        grey: np.ndarray,
        masks: BranchMasks | None,
        gates: dict[int, tuple[float, float]],
        timestamp_ns: int,
        origin: Origin,
        lost: bool,
        offsets: dict[int, tuple[float, float]] | None = None,
    ) -> None:
        """Note the frame just processed: the anchor the next frame is matched on (a keyframe's own grey
        image and instances; a tracked frame's keyframe's), the branches' disparity ranges, where this frame
        found them (`offsets`, px from the anchor) and whether it lost a branch."""
        if masks is None:
            self.reset()
            return
        keyframe_ns = timestamp_ns if origin == "keyframe" or self._carried is None else self._carried.keyframe_ns
        self._carried = CarriedFrame(grey, masks, gates, keyframe_ns, dict(offsets or {}))
        self._keyframe_due = self._keyframe_due or lost if origin == "tracked" else lost

    def reset(self) -> None:
        """Forget the carried instances: the next frame is a keyframe."""
        self._carried = None
        self._keyframe_due = True
        self._requested = False
