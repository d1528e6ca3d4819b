"""MAVLink 2 output to a flight controller: camera mount, message builders, link and relay.

`MavlinkRelay` is the object the daemon and the API use; `frames`, `messages` and `connection`
are its parts (geometry, encoding, transport), each usable and testable on its own.
"""

from branchrange.onboard.mavlink.frames import CameraMount
from branchrange.onboard.mavlink.relay import MavlinkRelay

__all__ = ["CameraMount", "MavlinkRelay"]
