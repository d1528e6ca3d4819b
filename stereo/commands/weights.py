"""`emcstereo weights list | fetch NAME | verify FILE`: released checkpoints, checked by SHA-256."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stereo.progress import progress_bar
from stereo.weights import REGISTRY, WeightsError, fetch_weights, get_weights_info, sha256_of


def _list(args: argparse.Namespace) -> int:
    for info in REGISTRY.values():
        size = f"{info.size_bytes / 1e6:.1f} MB" if info.size_bytes else "size unknown"
        print(
            f"{info.name}: {info.filename} ({info.layout} layout, {size})\n  sha256 {info.sha256}\n  {info.description}"
        )
        for split, metrics in info.metrics.items():
            print(f"  claims on {split}: " + ", ".join(f"{k} {v:g}" for k, v in metrics.items()))
    return 0


def _fetch(args: argparse.Namespace) -> int:
    try:
        info = get_weights_info(args.name)
        with progress_bar(unit="B", unit_scale=True, desc=info.filename, disable=args.quiet) as bar:

            def progress(done: int, total: int | None) -> None:
                bar.total = total
                bar.update(done - bar.n)

            path = fetch_weights(info, Path(args.dest), url=args.url, progress=progress)
    except WeightsError as exc:
        print(f"emcstereo weights fetch: {exc}", file=sys.stderr)
        return 1
    print(f"{path} verified (sha256 {info.sha256})")
    return 0


def _verify(args: argparse.Namespace) -> int:
    digest = sha256_of(Path(args.file))
    known = {info.sha256: info.name for info in REGISTRY.values()}
    if digest in known:
        print(f"{args.file}: matches {known[digest]}")
        return 0
    print(f"{args.file}: sha256 {digest} matches no registered weights", file=sys.stderr)
    return 1


def add_no_verify_flag(parser: argparse.ArgumentParser) -> None:
    """`--no-verify-weights` (sets `verify_sha256=False`) on a command that loads a checkpoint."""
    parser.add_argument(
        "--no-verify-weights",
        dest="verify_sha256",
        action="store_false",
        help="load a local file that carries a registered release's name without checking "
        "its SHA-256 against the registry",
    )


def register(sub: argparse._SubParsersAction) -> None:
    """Add `weights` to the `emcstereo` command."""
    parser = sub.add_parser("weights", help="list, download and verify released checkpoints")
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    actions.add_parser("list", help="the registered checkpoints and their claims").set_defaults(func=_list)
    fetch = actions.add_parser("fetch", help="download a checkpoint and verify its SHA-256")
    fetch.add_argument("name", help="registry name, e.g. emcstereo-virtualtree")
    fetch.add_argument("--url", help="download from this address instead of the registered one")
    fetch.add_argument("--dest", default="weights", help="folder to write into (default ./weights)")
    fetch.add_argument("--quiet", action="store_true", help="no progress bar")
    fetch.set_defaults(func=_fetch)
    verify = actions.add_parser("verify", help="say which registered checkpoint a file is")
    verify.add_argument("file")
    verify.set_defaults(func=_verify)
