"""The core: from a rectified stereo pair (or its disparity) and branch masks to a `FrameResult`.

Geometry (`geometry`), masks (`masks`), segmentation (`segmentation/`), cut points (`cutpoints`,
`cylinder_section`, `silhouette`), tracking (`tracking`), the typed result (`frame_result`), the
per-frame pipeline (`pipeline`, `frame_results`, `roi`, `pair_check`), the settings (`config`,
`settings_check`) and the result's picture (`overlay`). Imports only `stereo/`, `camera/` and itself:
never the onboard runtime, the offline tools, `api/` or the command line (tests/test_layers.py).
"""
