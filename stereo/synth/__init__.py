"""Synthetic stereo tree-branch scenes with exact ground truth, written in the VirtualTree layout.

`render_scene(seed, camera)` ray-casts one scene (trunk, branches, twigs, leaves, far foliage,
ground, sky) from both cameras of a rectified rig; `write_dataset` writes many of them as
`left image/`, `right image/`, `left depth/` (EXR, cm) plus masks and branch geometry.
"""

from stereo.synth.camera import SynthCamera
from stereo.synth.options import SynthOptions
from stereo.synth.render import SyntheticScene, render_scene
from stereo.synth.truth import LEAF_ID, MAX_BRANCH_ID, TRUNK_ID, TWIG_ID, BranchTruth, is_branch_id

__all__ = [
    "LEAF_ID",
    "MAX_BRANCH_ID",
    "TRUNK_ID",
    "TWIG_ID",
    "BranchTruth",
    "SynthCamera",
    "SynthOptions",
    "SyntheticScene",
    "is_branch_id",
    "render_scene",
]
