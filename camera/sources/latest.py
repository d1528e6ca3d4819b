"""Latest-frame-wins: a capture thread drains a live source so a slow consumer never gets stale frames."""

from __future__ import annotations

import threading
import time

from camera.sources.frame import SourceBase, SourceError, StereoFrame, StereoSource


class LatestFrameSource(SourceBase):
    """Wraps a source; a background thread reads it continuously and keeps only the newest frame.

    `next()` returns the newest frame not yet returned, waiting for one if needed; frames the
    consumer was too slow for are dropped (counted in `dropped`; the inner source's own drops, a paced
    replay's, in `dropped_late`). Recoverable SourceErrors of
    the inner source (CorruptFrameError, SourceDisconnected) are handed to the consumer by the
    next `next()` call and capture goes on; any other exception ends capture and is raised once,
    after which iteration stops. `get(timeout)` is `next()` with a timeout (None when nothing
    new came); `get_stamped` adds the frame's arrival time. `is_lost` and `calibration` are the inner
    source's. Closing closes the inner source.
    """

    def __init__(self, source: StereoSource) -> None:
        self.source = source
        self.calibration = source.calibration
        self.dropped = 0
        self._condition = threading.Condition()
        self._latest: StereoFrame | None = None
        self._received_at = 0.0  # time.monotonic() when the newest frame came out of the inner source
        self._errors: list[BaseException] = []
        self._finished = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._capture, name="latest-frame-capture", daemon=True)
        self._thread.start()

    @property
    def is_lost(self) -> bool:
        return self.source.is_lost

    @property
    def dropped_late(self) -> int:
        """The inner source's count of frames it dropped as too late (ReplaySource), 0 for one that has none."""
        return int(getattr(self.source, "dropped_late", 0))

    def _capture(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    frame = next(self.source)
                except StopIteration:
                    break
                except SourceError as error:
                    with self._condition:
                        self._errors.append(error)
                        self._condition.notify_all()
                    continue
                received_at = time.monotonic()
                with self._condition:
                    if self._latest is not None:
                        self.dropped += 1
                    self._latest, self._received_at = frame, received_at
                    self._condition.notify_all()
        except BaseException as error:  # handed to the consumer thread, which raises it
            with self._condition:
                self._errors.append(error)
        finally:
            with self._condition:
                self._finished = True
                self._condition.notify_all()

    def get(self, timeout: float | None = None) -> StereoFrame | None:
        """The newest unseen frame, waiting up to `timeout` s (None: forever); None on timeout.

        Raises StopIteration when the inner source has ended and everything was handed out.
        """
        stamped = self.get_stamped(timeout)
        return None if stamped is None else stamped[0]

    def get_stamped(self, timeout: float | None = None) -> tuple[StereoFrame, float] | None:
        """`get`, with the `time.monotonic()` seconds at which the frame left the inner source.

        That instant is the frame's capture time on this computer's clock (a camera's own
        timestamps may use another clock; a replay releases each frame at its recorded time), so
        the age of a result is measured from it.
        """
        with self._condition:
            ready = self._condition.wait_for(
                lambda: self._latest is not None or self._errors or self._finished, timeout
            )
            if not ready:
                return None
            if self._errors:
                raise self._errors.pop(0)
            if self._latest is None:
                raise StopIteration
            frame, self._latest = self._latest, None
            return frame, self._received_at

    def __next__(self) -> StereoFrame:
        frame = self.get()
        assert frame is not None  # get() without a timeout only returns a frame or raises
        return frame

    def close(self) -> None:
        """Stop the capture thread and close the inner source."""
        self._stop.set()
        self.source.close()
        self._thread.join(timeout=5.0)
