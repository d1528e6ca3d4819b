"""The training and validation datasets a config's `[data]` section describes."""

from __future__ import annotations

from stereo.datasets import SPLIT_FILE_DATASETS, StereoDataset, open_dataset
from stereo.datasets.splits import group_split, split_train_val
from stereo.training.config import ConfigError, DataSection


def train_val_datasets(data: DataSection) -> tuple[StereoDataset, StereoDataset]:
    """(train, val) raw-sample datasets: from split files, the seeded 90/10 split, or a group split."""
    if not data.root:
        raise ConfigError("data.root: empty; set it to the dataset folder (or pass --data-root)")
    if data.split == "files":
        if data.dataset not in SPLIT_FILE_DATASETS:
            raise ConfigError(
                f'data.split = "files" needs split files, which {data.dataset} does not have; use "paper" or "group"'
            )
        return open_dataset(data.dataset, data.root, data.train_split), open_dataset(
            data.dataset, data.root, data.val_split
        )
    full = open_dataset(data.dataset, data.root)
    if data.split == "paper":
        train_idx, val_idx = split_train_val(len(full), data.val_fraction, data.split_seed)
    else:
        train_idx, val_idx = group_split(full.names(), data.group_pattern, data.val_fraction, data.split_seed)
    return full.subset(train_idx), full.subset(val_idx)
