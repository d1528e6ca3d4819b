"""The onboard runtime: the daemon's threads (`daemon`, `newest_slot`), the MAVLink relay (`mavlink/`)
and the live Foxglove view (`foxglove_sink`, its layout `foxglove_layout`).

Imports the core, never the offline tools, `api/` or the command line; the API's metrics reach the
daemon through `daemon.DaemonMetrics` (tests/test_layers.py).
"""
