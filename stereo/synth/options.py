"""Options of the synthetic scene generator, validated once, with the defaults the dataset uses."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

POSES = ("auto", "upward", "parallel", "downward")
FOLIAGE = ("auto", "bare", "sparse", "dense")
LEAF_SHAPES = ("broad", "needles", "auto")
#: scene domains: "park", the one tree form, barks and light the shipped segmenter was trained on; "orchard", a
#: shifted domain it never saw (`stereo.synth.orchard`)
DOMAINS = ("park", "orchard")


@dataclass(frozen=True)
class SynthOptions:
    """How scenes are drawn and rendered.

    - `cut_offset_m`: the truth cut point lies this far from the branch base (where the branch
      leaves the trunk surface) along the axis toward the tip — pruning cuts just outside the
      branch collar, a few centimetres out (design.md "Cut points").
    - `supersample`: rays per pixel side for the images (2 → 4 rays per pixel); ground truth
      (depth, disparity, masks) always comes from the single ray through each pixel centre.
    - `pose`: camera pitch class ('upward', 'parallel', 'downward'), or 'auto' to draw one.
    - `foliage`: leaves on the twigs ('bare', 'sparse', 'dense'), or 'auto' to draw one.
    - `leaf_shape`: 'broad' leaf blades, 'needles' (clusters of conifer needles, thin tapered
      cylinders fanning out from the twigs), or 'auto' to draw one per scene. The default
      'broad' draws nothing extra, so scenes of a seed stay as they were before the option.
    - `background_trees`: mid-ground trees 4.5–9 m away (mask id 0, not pruning targets).
    - `orchard_hardware`: also draw trellis wires, posts, a stake and painted rods around the tree
      (`stereo.synth.hardware`; background, mask id 0): straight man-made things at the tree's depth that
      a pruner must not cut. Off by default, so the scenes of a seed stay as they were before the option.
    - `domain`: "park" (the default: the scenes the shipped segmenter was trained and calibrated on) or
      "orchard", a domain it never saw, for measuring how a model copes with a new orchard and for proving a
      fine-tune on one (`stereo.synth.orchard`): an espalier-trained tree whose branches run along the row's
      trellis wires, with posts and a row of trees behind, other barks (plated, banded, mossy), other leaf
      colours, and a low warm sun or a dim blue overcast. The default draws nothing differently, so the scenes
      of a seed stay as they were before the option.
    - `noise_std`: sensor noise, standard deviation in 8-bit grey levels, drawn per view.
    - `view_gain_jitter`: largest relative gain difference per colour channel between the views.
    - `threads`: render the left, right and ground-truth passes in this many threads (the
      result does not depend on it).
    """

    cut_offset_m: float = 0.05
    supersample: int = 2
    pose: str = "auto"
    foliage: str = "auto"
    leaf_shape: str = "broad"
    background_trees: bool = True
    orchard_hardware: bool = False
    domain: str = "park"
    noise_std: float = 1.0
    view_gain_jitter: float = 0.02
    threads: int = 2

    def __post_init__(self) -> None:
        if not 0.0 <= self.cut_offset_m <= 0.15:
            raise ValueError(
                f"cut_offset_m must lie in [0, 0.15] m (branches are ≥ 0.2 m long), got {self.cut_offset_m}"
            )
        if int(self.supersample) != self.supersample or not 1 <= self.supersample <= 4:
            raise ValueError(f"supersample must be an integer from 1 to 4 rays per pixel side, got {self.supersample}")
        if self.pose not in POSES:
            raise ValueError(f"pose must be one of {POSES}, got {self.pose!r}")
        if self.foliage not in FOLIAGE:
            raise ValueError(f"foliage must be one of {FOLIAGE}, got {self.foliage!r}")
        if self.leaf_shape not in LEAF_SHAPES:
            raise ValueError(f"leaf_shape must be one of {LEAF_SHAPES}, got {self.leaf_shape!r}")
        if self.domain not in DOMAINS:
            raise ValueError(f"domain must be one of {DOMAINS}, got {self.domain!r}")
        if not 0.0 <= self.noise_std <= 20.0:
            raise ValueError(f"noise_std must lie in [0, 20] grey levels, got {self.noise_std}")
        if int(self.threads) != self.threads or not 1 <= self.threads <= 3:
            raise ValueError(f"threads must be 1, 2 or 3, got {self.threads}")
        if not 0.0 <= self.view_gain_jitter <= 0.2:
            raise ValueError(f"view_gain_jitter must lie in [0, 0.2], got {self.view_gain_jitter}")

    @classmethod
    def from_mapping(cls, values: dict[str, Any]) -> SynthOptions:
        """Options from keyword values; an unknown key raises TypeError naming it and the known ones."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise TypeError(f"unknown synth option(s) {unknown}; known options: {sorted(known)}")
        return cls(**values)
