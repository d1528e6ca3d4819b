"""Run by tests/test_clock_jump.py under the wall-clock shim (`wall_clock_shim`): the relay's freshness
decisions while this process's wall clock jumps an hour either way. Prints one JSON object.

    python tests/clock_jump_case.py OFFSET_FILE

For each jump (+1 h, then −1 h from there): a result is published (captured now), the wall clock
jumps at once, and the DEBUG_VECT "CUT" sets the loopback autopilot receives in the next second are
noted as (seconds since the publish, target or not). Also noted: how far the wall clock moved beyond
the monotonic one across each jump (the proof the shim is in force).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

from mavlink_peer import LoopbackPeer, of_type
from result_factory import branch, frame_result
from wall_clock_shim import set_offset

from branchrange.config.sections import MavlinkConfig, TrackingConfig
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay

MAX_AGE_S = 0.3
RESULT = frame_result([branch(0, [0.1, -0.2, 1.4])], target_id=0)
JUMPS_S = (3600.0, -3600.0)


def main(offset_file: Path) -> dict[str, object]:
    peer = LoopbackPeer()
    cfg = MavlinkConfig(url=f"udpout:127.0.0.1:{peer.port}", max_result_age_s=MAX_AGE_S, send_rate_hz=20.0)
    tracking = TrackingConfig(target_min_observations=1)
    relay = MavlinkRelay(cfg, CameraMount.from_rpy((0, 0, 0), (0.0, 0.0, 0.0)), tracking=tracking)
    phases, offset = [], 0.0
    try:
        peer.collect(0.3)  # the first sets (no target yet)
        for jump in JUMPS_S:
            offset += jump
            wall, mono = time.time(), time.monotonic()
            relay.publish(RESULT)
            set_offset(offset_file, offset)
            got = of_type(peer.collect(1.0), "DEBUG_VECT")
            moved = (time.time() - wall) - (time.monotonic() - mono)
            sets = [[round(v.at - mono, 3), not math.isnan(v.msg.x)] for v in got]
            phases.append({"jump_s": jump, "wall_moved_s": round(moved, 1), "sets": sets})
    finally:
        relay.close()
        peer.close()
    return {"max_result_age_s": MAX_AGE_S, "phases": phases}


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]))))
