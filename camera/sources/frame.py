"""What every frame source yields and promises: `StereoFrame`, the `StereoSource` protocol, its errors.

A source is an iterator of `StereoFrame`. `next()` blocks until the next pair is there and raises
StopIteration when the source is finished or closed. A live source that loses its camera either
keeps trying to reconnect (while `is_lost` is True; `next()` blocks meanwhile) or raises
`SourceDisconnected`; a frame that cannot be decoded raises `CorruptFrameError` for that frame
only, and the next `next()` call moves on. Sources are context managers; `close()` is idempotent.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from camera.calibration import StereoCalibration


@dataclass(frozen=True, eq=False)
class StereoFrame:
    """One stereo pair: `left`, `right` H×W×3 uint8 RGB; `timestamp_ns` monotonic ns at capture; `index` ≥ 0.

    `mask`: the left view's branch mask (uint8/uint16 H×W, instance ids or binary) when the frame
    comes with one — a recording of synthetic or annotated data; None from live cameras.
    """

    left: np.ndarray
    right: np.ndarray
    timestamp_ns: int
    index: int
    mask: np.ndarray | None = None

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of each view, pixels."""
        return int(self.left.shape[1]), int(self.left.shape[0])


class SourceError(RuntimeError):
    """Base of the errors a frame source raises."""


class SourceUnavailable(SourceError):
    """The camera or recording cannot be opened at all (wrong device, missing files, no driver)."""


class SourceConfigError(SourceError, ValueError):
    """A source was given options it cannot honour (unknown mode, unsupported fps, bad spec)."""


class SourceDisconnected(SourceError):
    """The camera went away; the source may come back (see its `is_lost`)."""


class CorruptFrameError(SourceError):
    """One frame could not be decoded; the source itself is fine and the next frame may be read."""


@runtime_checkable
class StereoSource(Protocol):
    """The interface of every frame source (see the module docstring for the semantics)."""

    calibration: StereoCalibration | None

    @property
    def is_lost(self) -> bool: ...

    def __iter__(self) -> StereoSource: ...

    def __next__(self) -> StereoFrame: ...

    def close(self) -> None: ...


class SourceBase(ABC):
    """Iterator and context-manager plumbing shared by the sources; subclasses define `__next__` and `close`."""

    calibration: StereoCalibration | None = None

    @property
    def is_lost(self) -> bool:
        """True while the camera is gone and the source is waiting for it to come back."""
        return False

    @property
    def dropped_late(self) -> int:
        """Frames the source itself dropped for being too late to release (a paced replay); 0 for a camera,
        whose driver drops frames unseen and uncounted."""
        return 0

    def __iter__(self) -> SourceBase:
        return self

    @abstractmethod
    def __next__(self) -> StereoFrame:
        """The next stereo pair (blocking); StopIteration at the end or after close()."""

    @abstractmethod
    def close(self) -> None:
        """Release the camera or files; idempotent."""

    def __enter__(self) -> SourceBase:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class Backoff:
    """Exponential reconnection delays: `initial_s`, ×`factor` per failure, capped at `max_s`."""

    def __init__(self, initial_s: float = 0.1, factor: float = 2.0, max_s: float = 5.0) -> None:
        if initial_s <= 0 or factor < 1 or max_s < initial_s:
            raise SourceConfigError(
                f"backoff needs 0 < initial_s ≤ max_s and factor ≥ 1, got "
                f"initial_s={initial_s}, factor={factor}, max_s={max_s}"
            )
        self.initial_s, self.factor, self.max_s = initial_s, factor, max_s
        self._next = initial_s

    def next_delay(self) -> float:
        """The delay before the next attempt, seconds; each call grows the following one."""
        delay = self._next
        self._next = min(self._next * self.factor, self.max_s)
        return delay

    def reset(self) -> None:
        """Start again from `initial_s` (after a success)."""
        self._next = self.initial_s
