"""Train/validation splits: the authors' seeded 90/10 split and a group-aware (tree-/scene-disjoint) split.

The paper's open-dataset split shuffles the indices `0..N-1` with Python's `random.Random(seed)`
and holds out the first `max(1, round(0.1·N))` of them; both parts keep the original order.
The group-aware split holds out whole groups — all frames of one tree, scene or sequence, the id
taken from each record name by a regular expression — the tree-disjoint split the paper names as
missing.
"""

from __future__ import annotations

import random
import re
from collections.abc import Sequence

from stereo.datasets.base import DatasetError


def held_out_count(n: int, val_fraction: float) -> int:
    """How many of `n` items (or groups) a validation part of `val_fraction` holds: max(1, round(f·n))."""
    if not 0.0 < val_fraction < 1.0:
        raise DatasetError(f"val_fraction {val_fraction!r}: expected a fraction strictly between 0 and 1")
    return max(1, int(round(n * val_fraction)))


def split_train_val(n: int, val_fraction: float = 0.1, seed: int = 0) -> tuple[list[int], list[int]]:
    """(train, val) indices of `n` items by the authors' rule; both lists ascending."""
    if n < 2:
        raise DatasetError(f"cannot split {n} item(s) into train and val: need at least 2")
    order = list(range(n))
    random.Random(seed).shuffle(order)
    held_out = set(order[: held_out_count(n, val_fraction)])
    return [i for i in range(n) if i not in held_out], [i for i in range(n) if i in held_out]


def compile_group_pattern(pattern: str | re.Pattern[str]) -> re.Pattern[str]:
    """The compiled group pattern, or DatasetError naming it when it is not a valid regular expression."""
    try:
        return re.compile(pattern)
    except re.error as exc:
        raise DatasetError(f"group pattern {pattern!r}: not a valid regular expression ({exc})") from exc


def group_id(name: str, pattern: str | re.Pattern[str]) -> str:
    """The group id in `name`: the regex's first capture group, or the whole match without groups."""
    regex = compile_group_pattern(pattern)
    match = regex.search(name)
    if match is None:
        raise DatasetError(f"group pattern {regex.pattern!r} does not match record name {name!r}")
    return match.group(1) if regex.groups else match.group(0)


def group_split(
    names: Sequence[str], pattern: str, val_fraction: float = 0.1, seed: int = 0
) -> tuple[list[int], list[int]]:
    """(train, val) indices with no group on both sides; `max(1, round(f·G))` of the G groups held out."""
    regex = compile_group_pattern(pattern)
    ids = [group_id(name, regex) for name in names]
    groups = sorted(set(ids))
    if len(groups) < 2:
        raise DatasetError(
            f"group pattern {pattern!r} finds {len(groups)} group(s) in {len(names)} names; need at least 2 to split"
        )
    random.Random(seed).shuffle(groups)
    held_out = set(groups[: held_out_count(len(groups), val_fraction)])
    return (
        [i for i, g in enumerate(ids) if g not in held_out],
        [i for i, g in enumerate(ids) if g in held_out],
    )
