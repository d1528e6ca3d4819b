"""branchrange: from a stereo pair and branch masks to 3D cut points, and how they reach a drone.

The per-frame pipeline (`branchrange.pipeline.Pipeline`), cut-point geometry, masks and the
built-in segmenter, tracking, the MAVLink relay, the onboard daemon, offline replay and the
`branchrange` command line.
"""
