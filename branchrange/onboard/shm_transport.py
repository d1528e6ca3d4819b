"""Objects between processes with their arrays in shared memory: only a small pickle goes through the pipe.

A stereo frame at HD720 is 2 × 1280×720×3 bytes (5.5 MB) and the stereo stage's output about 14 MB
(left, right, disparity, confidence, labels); pickling them through a pipe copies each byte twice more
and holds the interpreter lock while it does. Here the object is pickled with protocol 5, whose
out-of-band buffers (numpy arrays' data) are written into a shared-memory block the writer owns and
grows as needed; the pipe carries the pickle's small rest, the block's name and each buffer's offset
and size (`Packed`). The reader copies the buffers out before the writer may reuse its block, so the
object it gets owns its memory.

The protocol is one object in flight per direction: the writer writes again only after the reader
answered (the stereo workers' request / reply), which is what makes reusing one block safe. Processes
started by `multiprocessing` share their parent's resource tracker, so a block whose writer was killed
is still freed: by the reader (`ShmReader.close(unlink=True)`), or at the latest when the parent ends.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from multiprocessing import shared_memory
from typing import Any

#: Buffers smaller than this (bytes) stay in the pickle: a shared-memory round trip is not worth it.
IN_BAND_BYTES = 4096
#: A grown block gets this much room beyond what the object needs, so a slightly larger frame does not grow it again.
GROWTH = 1.25


@dataclass(frozen=True)
class Packed:
    """What goes through the pipe: the pickle (`data`), the shared-memory block's name, and each out-of-band
    buffer's (offset, size) in bytes within it."""

    data: bytes
    block: str | None
    spans: tuple[tuple[int, int], ...]


class ShmWriter:
    """Packs objects into one shared-memory block of its own (created, grown and unlinked by it)."""

    def __init__(self) -> None:
        self._block: shared_memory.SharedMemory | None = None

    def pack(self, obj: Any) -> Packed:
        """`obj` pickled, its large buffers copied into the block."""
        buffers: list[pickle.PickleBuffer] = []

        def out_of_band(buffer: pickle.PickleBuffer) -> bool:
            if buffer.raw().nbytes < IN_BAND_BYTES:
                return True  # serialised in band
            buffers.append(buffer)
            return False

        data = pickle.dumps(obj, protocol=5, buffer_callback=out_of_band)
        if not buffers:
            return Packed(data, None, ())
        raws = [buffer.raw() for buffer in buffers]
        block = self._room(sum(raw.nbytes for raw in raws))
        view = _view(block)
        spans, offset = [], 0
        for raw in raws:
            view[offset : offset + raw.nbytes] = raw
            spans.append((offset, raw.nbytes))
            offset += raw.nbytes
        return Packed(data, block.name, tuple(spans))

    def _room(self, nbytes: int) -> shared_memory.SharedMemory:
        if self._block is None or self._block.size < nbytes:
            self.close()
            self._block = shared_memory.SharedMemory(create=True, size=max(1, int(nbytes * GROWTH)))
        return self._block

    def close(self) -> None:
        """Free the block (the readers' mappings stay valid until they close theirs)."""
        if self._block is not None:
            self._block.close()
            self._block.unlink()
            self._block = None


class ShmReader:
    """Unpacks `Packed` objects, attaching to each writer's block by name (the latest one per writer kept)."""

    def __init__(self) -> None:
        self._blocks: dict[str, shared_memory.SharedMemory] = {}

    def unpack(self, packed: Packed) -> Any:
        """The object, its buffers copied out of the block (so the writer may reuse it at once)."""
        if packed.block is None:
            return pickle.loads(packed.data)
        view = _view(self._attach(packed.block))
        buffers = [bytearray(view[offset : offset + size]) for offset, size in packed.spans]
        return pickle.loads(packed.data, buffers=buffers)

    def _attach(self, name: str) -> shared_memory.SharedMemory:
        block = self._blocks.get(name)
        if block is None:
            self.close()  # a writer grows by replacing its block: the old one is not used again
            block = shared_memory.SharedMemory(name=name)
            self._blocks[name] = block
        return block

    def close(self, unlink: bool = False) -> None:
        """Drop the mappings of the blocks attached so far; `unlink`: free them too (their writer died)."""
        for block in self._blocks.values():
            block.close()
            if unlink:
                try:
                    block.unlink()
                except FileNotFoundError:  # the writer freed it after all
                    pass
        self._blocks.clear()


def _view(block: shared_memory.SharedMemory) -> memoryview:
    """The bytes of an open block (its `buf` is None only once closed)."""
    view = block.buf
    assert view is not None, "a closed shared-memory block"
    return view
