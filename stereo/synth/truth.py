"""Ground truth of a synthetic scene that is not an image: instance ids and branch geometry.

Instance ids in the 16-bit masks: 0 is background (sky, ground, far foliage, mid-ground trees),
1..N are the pruning-target branches in `branches` order, and the top of the range is reserved:
`TRUNK_ID` (65535) the main trunk, `TWIG_ID` (65534) the thin twigs growing from the branches,
`LEAF_ID` (65533) their leaves or needles. A branch's own pixels are its tapered axis cylinder only, so a
line fit through them recovers its axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TRUNK_ID = 65535
TWIG_ID = 65534
LEAF_ID = 65533
#: Largest id a branch can have.
MAX_BRANCH_ID = LEAF_ID - 1

Vector = tuple[float, float, float]


def is_branch_id(ids: np.ndarray) -> np.ndarray:
    """Boolean array: which mask values are pruning-target branches (not background, trunk, twig or leaf)."""
    ids = np.asarray(ids)
    return (ids >= 1) & (ids <= MAX_BRANCH_ID)


@dataclass(frozen=True)
class BranchTruth:
    """One branch, in the rectified left camera frame (metres; x right, y down, z forward).

    `base_m` is where the branch axis leaves the trunk surface, `direction` the unit axis toward
    the tip, `length_m` the axis length from base to tip, radii at base and tip, and
    `cut_point_m = base_m + offset · direction` (offset: `SynthOptions.cut_offset_m`).
    `cut_pixel` is the cut point projected into the left image (x, y px), `cut_visible` whether
    the left mask shows this branch at that pixel, `mask_pixels` the branch's pixel count.
    """

    id: int
    base_m: Vector
    direction: Vector
    length_m: float
    base_radius_m: float
    tip_radius_m: float
    cut_point_m: Vector
    cut_pixel: tuple[float, float] = (float("nan"), float("nan"))
    cut_visible: bool = False
    mask_pixels: int = 0

    @property
    def tip_m(self) -> Vector:
        """The tip end of the axis (m)."""
        tip = np.asarray(self.base_m) + self.length_m * np.asarray(self.direction)
        return (float(tip[0]), float(tip[1]), float(tip[2]))

    @property
    def cut_offset_m(self) -> float:
        """Distance from base to cut point along the axis (m)."""
        return float(np.linalg.norm(np.asarray(self.cut_point_m) - np.asarray(self.base_m)))

    def radius_at(self, s_m: float) -> float:
        """Axis radius (m) at `s_m` metres from the base."""
        return self.base_radius_m + (self.tip_radius_m - self.base_radius_m) * s_m / self.length_m

    def to_dict(self) -> dict[str, object]:
        """JSON-ready description (lists of floats; metres and pixels)."""
        return {
            "id": self.id,
            "base_m": list(self.base_m),
            "direction": list(self.direction),
            "length_m": self.length_m,
            "base_radius_m": self.base_radius_m,
            "tip_radius_m": self.tip_radius_m,
            "tip_m": list(self.tip_m),
            "cut_point_m": list(self.cut_point_m),
            "cut_offset_m": self.cut_offset_m,
            "cut_pixel": list(self.cut_pixel),
            "cut_visible": self.cut_visible,
            "mask_pixels": self.mask_pixels,
        }
