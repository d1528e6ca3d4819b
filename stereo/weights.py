"""Released weights as data: name, file, SHA-256, layout and the metrics they claim.

Nothing downloads implicitly: `fetch_weights` runs only when a user asks (`emcstereo weights
fetch`). A download goes to a temporary file beside the destination and becomes the real file
only after its size and SHA-256 check out, so no partial or unverified file is ever left behind.
A file that carries a registered file name is checked again on every load (`registered_as`,
`cached_sha256`, used by `stereo.checkpoints.load_model`), hashed once per size and mtime.
"""

from __future__ import annotations

import hashlib
import http.client
import os
import tempfile
import urllib.error
import urllib.request
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

CHUNK = 1 << 20


@dataclass(frozen=True)
class WeightsInfo:
    """One released checkpoint and what it claims."""

    name: str
    filename: str
    sha256: str
    layout: str
    url: str
    size_bytes: int | None = None
    variant: dict[str, bool | int] = field(default_factory=dict)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    description: str = ""


REGISTRY: dict[str, WeightsInfo] = {
    info.name: info
    for info in (
        WeightsInfo(
            name="emcstereo-virtualtree",
            filename="emcstereo_virtualtree_best.pth",
            sha256="bc2e591d9138ab09af2023fbf313c1b54bac0dcd955fe2264fd6290a93d68747",
            layout="authors",
            url="https://github.com/stereo-tree-pruning/EMCStereo/raw/main/checkpoints/emcstereo_virtualtree_best.pth",
            size_bytes=61_866_765,
            variant={"ema": True, "msf": True, "coord": True, "max_disp": 192},
            metrics={
                "virtualtree/val": {
                    "epe": 1.314849,
                    "d1_all": 0.058010,
                    "bad_1": 0.153278,
                    "bad_3": 0.073348,
                    "rmse": 4.825643,
                    "abs_rel": 0.056242,
                    "delta1": 0.962039,
                },
                "virtualtree/test": {
                    "epe": 1.307740,
                    "d1_all": 0.059573,
                    "bad_1": 0.151631,
                    "bad_3": 0.073064,
                    "rmse": 4.707669,
                    "abs_rel": 0.056088,
                    "delta1": 0.961051,
                },
            },
            description="The authors' deployed EMCStereo (epoch 252 on VirtualTree); input RGB in [0,1], "
            "ImageNet-normalised, padded top/right to a multiple of 32.",
        ),
    )
}


class WeightsError(RuntimeError):
    """A download that failed or did not verify; nothing was left at the destination."""


def get_weights_info(name: str) -> WeightsInfo:
    """The registry entry called `name`, or an error listing the known names."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise WeightsError(f"unknown weights {name!r}; known: {', '.join(sorted(REGISTRY))}") from None


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of a file, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for chunk in iter(lambda: stream.read(CHUNK), b""):
            digest.update(chunk)
    return digest.hexdigest()


def registered_as(path: Path, registry: Mapping[str, WeightsInfo] = REGISTRY) -> WeightsInfo | None:
    """The registry entry whose file name `path` carries (what `fetch_weights` writes), or None for a local file."""
    return next((info for info in registry.values() if info.filename == path.name), None)


#: SHA-256 of the files hashed in this process, by (real path, device, inode, size, mtime in ns).
_DIGESTS: dict[tuple[str, int, int, int, int], str] = {}


def cached_sha256(path: Path) -> str:
    """`sha256_of(path)`, computed once per file version: a file whose size or mtime changed is hashed again.

    Loading the same 62 MB release in every backend a process builds then costs one read, not one each.
    """
    stat = path.stat()
    key = (str(path.resolve()), stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)
    digest = _DIGESTS.get(key)
    if digest is None:
        digest = _DIGESTS[key] = sha256_of(path)
    return digest


def fetch_weights(
    info: WeightsInfo,
    dest_dir: Path,
    *,
    url: str | None = None,
    timeout_s: float = 30.0,
    progress: Callable[[int, int | None], None] | None = None,
) -> Path:
    """Download `info` into `dest_dir`, verify it, and return the final path.

    An already present file with the right checksum is kept without downloading.
    `progress(bytes_so_far, total_or_None)` is called as chunks arrive.
    """
    dest_dir.mkdir(parents=True, exist_ok=True)
    target = dest_dir / info.filename
    if target.is_file() and sha256_of(target) == info.sha256:
        return target
    source = url or info.url
    fd, tmp_name = tempfile.mkstemp(prefix=f".{info.filename}.", suffix=".part", dir=dest_dir)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as out:
            digest, received = _download(source, out, timeout_s, progress)
        _verify(info, source, digest, received)
        os.replace(tmp, target)
        return target
    finally:
        tmp.unlink(missing_ok=True)


def _download(
    url: str, out: BinaryIO, timeout_s: float, progress: Callable[[int, int | None], None] | None
) -> tuple[str, int]:
    digest = hashlib.sha256()
    received = 0
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as response:
            total = response.length
            while chunk := response.read(CHUNK):
                out.write(chunk)
                digest.update(chunk)
                received += len(chunk)
                if progress:
                    progress(received, total)
            if total is not None and received < total:
                raise WeightsError(f"{url}: connection closed after {received} of {total} bytes")
    except (urllib.error.URLError, http.client.HTTPException, OSError, ValueError) as exc:
        raise WeightsError(f"{url}: download failed after {received} bytes: {exc!r}") from exc
    return digest.hexdigest(), received


def _verify(info: WeightsInfo, url: str, digest: str, received: int) -> None:
    if info.size_bytes is not None and received != info.size_bytes:
        raise WeightsError(f"{url}: got {received} bytes, expected {info.size_bytes} for {info.name}; file discarded")
    if digest != info.sha256:
        raise WeightsError(f"{url}: SHA-256 {digest} does not match {info.sha256} for {info.name}; file discarded")
