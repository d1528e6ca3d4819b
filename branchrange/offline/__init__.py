"""The offline tools: replay of a recording (`replay`), overlay videos (`overlay_video`), cut-point
evaluation against a truth (`evaluate_cuts`) and flight-recording truth files (`flight`).

Imports the core, never the onboard runtime, `api/` or the command line (tests/test_layers.py).
"""
