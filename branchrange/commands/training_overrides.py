"""`--set KEY=VALUE` for the segmenter's training settings, shared by `train-segmenter` and its `--coco`
fine-tune (`branchrange.commands.finetune_segmenter`): each value is JSON, each key one of the settings
dataclass's fields."""

from __future__ import annotations

import json


def parsed_overrides(known: set[str], overrides: list[str]) -> dict:
    """KEY=VALUE items (`--set`) as {key: JSON value}; ValueError naming an item whose key is not in `known` or
    whose value is not JSON."""
    values = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or key not in known:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(known))}")
        try:
            values[key] = json.loads(text)
        except ValueError:
            raise ValueError(f"--set {key}: {text!r} is not a JSON value (numbers as 3, lists as [1, 2])") from None
    return values
