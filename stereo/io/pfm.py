"""PFM (portable float map) reading and writing: SceneFlow, ETH3D and Middlebury disparities.

Format: a header of four whitespace-separated tokens — `Pf` (grey) or `PF` (colour), width,
height, scale — then float32 pixels, rows stored bottom-up. The scale's sign gives the byte order
(negative: little-endian); its magnitude is not applied to the data, as the open-dataset tools do.
OpenCV's reader mishandles some of these files, hence this parser.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereo.io.errors import ArrayFormatError, MalformedFileError

_CHANNELS = {b"Pf": 1, b"PF": 3}
_HEADER_TOKENS = 4
_WHITESPACE = b" \t\r\n"


def _header_tokens(data: bytes, path: Path) -> tuple[list[bytes], int]:
    """The four header tokens of a PFM file and the offset just past the last one."""
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < _HEADER_TOKENS:
        while pos < len(data) and data[pos] in _WHITESPACE:
            pos += 1
        start = pos
        while pos < len(data) and data[pos] not in _WHITESPACE and pos - start < 32:
            pos += 1
        if start == pos:
            raise MalformedFileError(
                f"{path}: PFM header ends after {len(tokens)} of 4 tokens (magic, width, height, scale)"
            )
        tokens.append(data[start:pos])
    return tokens, pos


def read_pfm(path: str | Path, *, all_channels: bool = False) -> np.ndarray:
    """Read a PFM file as float32, top row first.

    Returns `H×W` — for a colour (`PF`) file its channel 0, which is how disparity stored in colour
    PFMs is read — or, with `all_channels=True`, `H×W×C` with C = 1 or 3 as stored.
    """
    path = Path(path)
    data = path.read_bytes()
    (magic, width_tok, height_tok, scale_tok), header_end = _header_tokens(data, path)
    if magic not in _CHANNELS:
        raise MalformedFileError(f"{path}: not a PFM file, magic {magic[:8]!r} is neither b'Pf' nor b'PF'")
    try:
        width, height, scale = int(width_tok), int(height_tok), float(scale_tok)
    except ValueError as exc:
        raise MalformedFileError(
            f"{path}: PFM header size/scale {width_tok!r} {height_tok!r} {scale_tok!r} are not numbers"
        ) from exc
    if width <= 0 or height <= 0:
        raise MalformedFileError(f"{path}: PFM size {width}×{height} must be positive")
    if scale == 0.0 or not np.isfinite(scale):
        raise MalformedFileError(
            f"{path}: PFM scale {scale_tok!r} must be non-zero and finite (its sign is the byte order)"
        )
    channels = _CHANNELS[magic]
    n_bytes = width * height * channels * 4
    # The pixel block is the last n_bytes; only whitespace may separate it from the header.
    offset = len(data) - n_bytes
    if offset <= header_end:
        raise MalformedFileError(
            f"{path}: truncated PFM, {width}×{height}×{channels} float32 needs {n_bytes} bytes of pixels, "
            f"found {max(len(data) - header_end - 1, 0)}"
        )
    if any(b not in _WHITESPACE for b in data[header_end:offset]):
        raise MalformedFileError(
            f"{path}: {offset - header_end} unexpected bytes between the PFM header and its pixels"
        )
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    pixels = np.frombuffer(data, dtype=dtype, count=width * height * channels, offset=offset)
    image = pixels.reshape(height, width, channels)[::-1].astype(np.float32)
    return image if all_channels else np.ascontiguousarray(image[:, :, 0])


def write_pfm(path: str | Path, array: np.ndarray, *, little_endian: bool = True) -> None:
    """Write a float `H×W` (grey, `Pf`) or `H×W×3` (colour, `PF`) array as PFM, rows bottom-up, scale ±1."""
    path = Path(path)
    array = np.asarray(array)
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3) or array.size == 0:
        raise ArrayFormatError(f"cannot write {path}: PFM stores H×W or H×W×3 arrays, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ArrayFormatError(f"cannot write {path}: PFM stores float32 values, got dtype {array.dtype}")
    magic = "Pf" if array.ndim == 2 else "PF"
    height, width = array.shape[:2]
    dtype = np.dtype("<f4") if little_endian else np.dtype(">f4")
    header = f"{magic}\n{width} {height}\n{-1.0 if little_endian else 1.0}\n".encode("ascii")
    path.write_bytes(header + np.ascontiguousarray(array[::-1], dtype=dtype).tobytes())
