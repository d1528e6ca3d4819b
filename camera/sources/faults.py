"""Fault injection around any frame source, for testing what consumes frames (the daemon, the pipeline).

Usage::

    from camera.sources import ReplaySource, FaultInjectingSource, FaultPlan

    plan = FaultPlan(drop={3, 4},            # frames 3 and 4 vanish (the consumer sees a gap in index)
                     stall={6: 0.5},         # frame 6 arrives 0.5 s late (is_lost stays False)
                     disconnect={10: 2.0},   # before frame 10 the camera is gone for 2 s
                     corrupt={12},           # frame 12 cannot be decoded: next() raises CorruptFrameError
                     repeat={14: 3})         # frame 14 comes again instead of the next 3 (a frozen driver buffer)
    with FaultInjectingSource(ReplaySource(path, pace="fast"), plan) as source:
        for frame in source: ...

Positions count the frames pulled from the wrapped source, from 0 (for a ReplaySource started at
frame 0 without looping, position == StereoFrame.index). Each fault fires once.

Disconnects: with `FaultPlan.disconnect_raises=False` (default) `next()` blocks for the outage with
`is_lost` True, as a live source that reconnects does, then delivers the frame. With
`disconnect_raises=True`, every `next()` during the outage raises SourceDisconnected at once
(`is_lost` True) and the first call after it delivers the frame: the behaviour of a source that
does not reconnect by itself. A corrupt frame raises CorruptFrameError once; the following
`next()` goes on with the next frame. A repeated frame comes again, the same object (index,
timestamp and images), in place of as many following frames as `repeat` says (pulled from the
wrapped source all the same, so a paced source keeps its pace). `injected` lists what fired, as (position, kind) pairs.
`sleep`/`clock` can be replaced in tests; by default waits end early when `close()` is called.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from camera.sources.frame import CorruptFrameError, SourceBase, SourceDisconnected, StereoFrame, StereoSource


@dataclass(frozen=True)
class FaultPlan:
    """Which faults to inject at which positions (see the module docstring)."""

    drop: frozenset[int] | set[int] = field(default_factory=frozenset)
    stall: Mapping[int, float] = field(default_factory=dict)
    disconnect: Mapping[int, float] = field(default_factory=dict)
    corrupt: frozenset[int] | set[int] = field(default_factory=frozenset)
    repeat: Mapping[int, int] = field(default_factory=dict)
    disconnect_raises: bool = False

    def __post_init__(self) -> None:
        if any(position < 0 or times < 1 for position, times in self.repeat.items()):
            raise ValueError(f"FaultPlan.repeat = {dict(self.repeat)}; expected position ≥ 0 and times ≥ 1")
        for name in ("stall", "disconnect"):
            for position, seconds in getattr(self, name).items():
                if position < 0 or seconds < 0:
                    raise ValueError(f"FaultPlan.{name}[{position}] = {seconds}; expected position ≥ 0 and seconds ≥ 0")
        for name in ("drop", "corrupt"):
            if any(position < 0 for position in getattr(self, name)):
                raise ValueError(f"FaultPlan.{name} = {sorted(getattr(self, name))}; expected positions ≥ 0")


class FaultInjectingSource(SourceBase):
    """A source that passes the wrapped source's frames through, injecting the faults of a FaultPlan."""

    def __init__(
        self,
        source: StereoSource,
        plan: FaultPlan,
        *,
        sleep: Callable[[float], Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.source = source
        self.plan = plan
        self.calibration = source.calibration
        self.injected: list[tuple[int, str]] = []
        self._stop = threading.Event()
        self._sleep = sleep or self._stop.wait
        self._clock = clock
        self._position = 0
        self._lost = False
        self._outage_end: float | None = None
        self._fired: set[tuple[int, str]] = set()
        self._frozen: StereoFrame | None = None  # a repeated frame, delivered in place of the next ones
        self._frozen_left = 0

    @property
    def is_lost(self) -> bool:
        return self._lost or self.source.is_lost

    def _fire(self, kind: str) -> bool:
        """True the first time fault `kind` is due at the current position."""
        key = (self._position, kind)
        due = {
            "drop": self._position in self.plan.drop,
            "stall": self._position in self.plan.stall,
            "disconnect": self._position in self.plan.disconnect,
            "corrupt": self._position in self.plan.corrupt,
            "repeat": self._position in self.plan.repeat,
        }[kind]
        if not due or key in self._fired:
            return False
        self._fired.add(key)
        self.injected.append(key)
        return True

    def _disconnect(self) -> None:
        """Block through the outage (is_lost True), or raise SourceDisconnected while it lasts."""
        if self._fire("disconnect"):
            self._lost = True
            self._outage_end = self._clock() + self.plan.disconnect[self._position]
            if not self.plan.disconnect_raises:
                self._sleep(self.plan.disconnect[self._position])
        if self._outage_end is not None and self.plan.disconnect_raises and self._clock() < self._outage_end:
            raise SourceDisconnected(f"injected disconnect before frame position {self._position}")
        self._outage_end = None
        self._lost = False

    def __next__(self) -> StereoFrame:
        while True:
            if self._stop.is_set():
                raise StopIteration
            self._disconnect()
            if self._fire("stall"):
                self._sleep(self.plan.stall[self._position])
            frame = next(self.source)
            position = self._position
            if self._frozen_left > 0 and self._frozen is not None:  # the wrapped source keeps its pace
                self._frozen_left -= 1
                self._position += 1
                return self._frozen
            if self._fire("drop"):
                self._position += 1
                continue
            if self._fire("corrupt"):
                self._position += 1
                raise CorruptFrameError(f"injected corrupt image at frame position {position} (index {frame.index})")
            if self._fire("repeat"):
                self._frozen, self._frozen_left = frame, self.plan.repeat[self._position]
            self._position += 1
            return frame

    def close(self) -> None:
        """Close the wrapped source; a wait in progress ends at once."""
        self._stop.set()
        self.source.close()
