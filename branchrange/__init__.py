"""branchrange: from a stereo pair and branch masks to 3D cut points, and how they reach a drone.

Layers, each importing only those below it (tests/test_layers.py):
- `cli.py`, `commands/`: the `branchrange` command line, on top (it may also import `api/`);
- `onboard/` (daemon, MAVLink relay, live Foxglove view) and `offline/` (replay, overlay videos,
  evaluation, flight truth), side by side, neither importing the other; `api/` beside them;
- `core/`: geometry, masks, segmentation, cut points, tracking, the typed result, the per-frame
  pipeline (`core.pipeline.Pipeline`) and the configuration;
- `stereo/` and `camera/` below everything.
"""
