"""A one-item mailbox between two threads where the newest item wins: the daemon's stereo → geometry
hand-over and the Foxglove sink's frames. A slow taker never works through a queue of stale items."""

from __future__ import annotations

import threading
from typing import Any


class NewestSlot:
    """A one-item mailbox between two threads: `put` replaces what the taker did not get to (counted).

    The taker calls `take()`, works on the item, then `task_done()`; `wait_idle()` waits until the
    mailbox is empty and the taker is not working on anything.
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._item: Any = None
        self._busy = False
        self._closed = False
        self.replaced = 0

    def put(self, item: Any) -> None:
        with self._condition:
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._condition.notify_all()

    def take(self) -> Any:
        """The item, waiting for one; None once closed and empty."""
        with self._condition:
            self._condition.wait_for(lambda: self._item is not None or self._closed)
            item, self._item = self._item, None
            self._busy = item is not None
            self._condition.notify_all()
            return item

    def task_done(self) -> None:
        with self._condition:
            self._busy = False
            self._condition.notify_all()

    def wait_idle(self) -> None:
        """Block until the mailbox is empty and the taker has finished its item."""
        with self._condition:
            self._condition.wait_for(lambda: (self._item is None and not self._busy) or self._closed)

    def close(self) -> None:
        with self._condition:
            self._closed = True
            self._condition.notify_all()
