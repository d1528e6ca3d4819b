"""`branchrange daemon` as the soak (`benchmarks/soak.py`) runs it: the shipped command, unchanged, whose
camera is a looping replay of a rendered flight with faults the soak sets while it runs.

    python benchmarks/soak_daemon.py --control-port PORT --epoch SECONDS -- daemon --config FILE --set ...

Everything after `--` goes to `branchrange` as it is; only `camera.sources.open_source` (what the
daemon opens its camera with, at start and on each reopening) is replaced by one that opens the
configured replay looping, at the frame the flight has reached since `--epoch` (a `time.monotonic()`
instant: CLOCK_MONOTONIC is one clock for every process of the machine), so a camera opened again
mid-flight sees the scene of that moment, as a real one would, and the soak's autopilot flies the
same flight. The recording's masks are left out (the configured segmenter finds the branches). Each
frame's `timestamp_ns` is the monotonic time it was captured (a V4L2 driver stamps frames so), which
the results log keeps: the soak compares it with when a target arrived.

Faults come as JSON datagrams on 127.0.0.1:`--control-port` and apply to whichever camera is open:
- `{"fault": "stall", "until": T}`: no frame until monotonic time T (the camera still says it is there; the
  frame being read when a stall or an unplug begins is not delivered either);
- `{"fault": "disconnect", "until": T}`: the camera is gone until T (`is_lost`; opening it fails);
- `{"fault": "corrupt", "frames": N}`: the next N frames cannot be decoded (CorruptFrameError);
- `{"fault": "identical", "frames": N}`: the next frame is delivered N + 1 times, timestamp and all (a
  frozen driver buffer), in place of the N frames captured meanwhile;
- `{"fault": "reorder", "frames": N}`: N pairs of consecutive frames arrive swapped (older after newer);
- `{"fault": "resize", "until": T}`: frames arrive at half the calibrated size until T.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time
from dataclasses import replace
from typing import Any

import cv2

import camera.sources
from camera.sources import CorruptFrameError, SourceBase, SourceUnavailable, StereoFrame

#: How often a wait checks whether its source was closed (s).
WAIT_STEP_S = 0.05


class CameraFaults:
    """The faults in force, shared by every camera the daemon opens; set from the control socket's thread."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.until = {"stall": 0.0, "disconnect": 0.0, "resize": 0.0}
        self.frames = {"corrupt": 0, "identical": 0, "reorder": 0}

    def apply(self, command: dict[str, Any]) -> None:
        """Take one control message (module docstring); unknown ones are reported, never fatal."""
        kind = command.get("fault")
        with self.lock:
            if kind in self.until:
                self.until[kind] = float(command["until"])
            elif kind in self.frames:
                self.frames[kind] += int(command["frames"])
            else:
                print(f"soak_daemon: unknown fault {command!r}", file=sys.stderr)

    def active(self, kind: str) -> float:
        """Seconds left of a timed fault (0 when not in force)."""
        return max(0.0, self.until[kind] - time.monotonic())

    def take(self, kind: str, every: bool = False) -> int:
        """How many of the counted faults of `kind` the next frame uses up: one, or `every` one pending."""
        with self.lock:
            taken = self.frames[kind] if every else min(1, self.frames[kind])
            self.frames[kind] -= taken
            return taken


class SoakCamera(SourceBase):
    """A looping replay with the soak's faults (module docstring); frames stamped with monotonic capture time."""

    def __init__(self, source: Any, faults: CameraFaults) -> None:
        self.source, self.faults = source, faults
        self.calibration = source.calibration
        self._closed = threading.Event()
        self._frozen: StereoFrame | None = None  # delivered again while `_repeats` > 0
        self._repeats = 0
        self._late: StereoFrame | None = None  # the older of a swapped pair, delivered next

    @property
    def is_lost(self) -> bool:
        return self.faults.active("disconnect") > 0

    def _wait_out(self, kind: str) -> None:
        while (left := self.faults.active(kind)) > 0 and not self._closed.is_set():
            self._closed.wait(min(left, WAIT_STEP_S))

    def _capture(self) -> StereoFrame:
        frame = next(self.source)  # without the rendered masks: the configured segmenter finds the branches
        return replace(frame, timestamp_ns=time.monotonic_ns(), mask=None)

    def __next__(self) -> StereoFrame:
        self._wait_out("disconnect")
        self._wait_out("stall")
        if self._closed.is_set():
            raise StopIteration
        if self._late is not None:
            late, self._late = self._late, None
            return late
        frame = self._capture()  # captured even when not delivered: the replay keeps its pace
        if self.faults.active("disconnect") > 0 or self.faults.active("stall") > 0:
            # unplugged or stalled while this frame was read (the replay's paced wait and HD720 decoding: up to
            # a second on a starved CPU): it never arrives, as from a real camera — delivered, it came stamped
            # 0.9 s into an unplug and the soak judged the daemon's "camera back" a status hiding the fault
            return next(self)
        if self._repeats > 0 and self._frozen is not None:
            self._repeats -= 1
            return self._frozen
        if repeats := self.faults.take("identical", every=True):
            self._frozen, self._repeats = frame, repeats
        elif self.faults.take("corrupt"):
            raise CorruptFrameError(f"soak: corrupt frame {frame.index}")
        elif self.faults.take("reorder"):
            self._late, frame = frame, self._capture()
        return self._resized(frame)

    def _resized(self, frame: StereoFrame) -> StereoFrame:
        if self.faults.active("resize") <= 0:
            return frame
        half = (frame.left.shape[1] // 2, frame.left.shape[0] // 2)
        return replace(frame, left=cv2.resize(frame.left, half), right=cv2.resize(frame.right, half), mask=None)

    def close(self) -> None:
        self._closed.set()
        self.source.close()


def soak_open_source(faults: CameraFaults, epoch: float, real_open: Any) -> Any:
    """`open_source` for the daemon: the configured replay, looping, from the flight's present frame."""

    def open_source(spec: str, **options: Any) -> Any:
        if faults.active("disconnect") > 0:
            raise SourceUnavailable(f"{spec}: camera unplugged (soak)")
        probe = real_open(spec, calibration=options.get("calibration"), pace="fast")
        count, fps = probe.frame_count, probe.fps
        probe.close()
        start = int((time.monotonic() - epoch) * fps) % count
        source = real_open(spec, calibration=options.get("calibration"), pace="recorded", loop=True, start=start)
        return SoakCamera(source, faults)

    return open_source


def listen(port: int, faults: CameraFaults) -> None:
    """The control socket's thread: each datagram one JSON fault (module docstring)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    while True:
        data = sock.recv(4096)
        try:
            faults.apply(json.loads(data))
        except (ValueError, KeyError, TypeError) as error:
            print(f"soak_daemon: bad control message {data!r}: {error}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--control-port", type=int, required=True, help="UDP port on 127.0.0.1 for the faults")
    parser.add_argument("--epoch", type=float, required=True, help="time.monotonic() of the flight's frame 0")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the branchrange command line")
    args = parser.parse_args(argv)
    faults = CameraFaults()
    threading.Thread(target=listen, args=(args.control_port, faults), name="soak-control", daemon=True).start()
    camera.sources.open_source = soak_open_source(faults, args.epoch, camera.sources.open_source)
    from branchrange.cli import main as branchrange_main

    return branchrange_main(args.command[1:] if args.command[:1] == ["--"] else args.command)


if __name__ == "__main__":
    sys.exit(main())
