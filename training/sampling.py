"""Which training windows an epoch visits, and in what order.

Overlapping windows (a new one every ``hop`` samples) repeat most of their samples, so an epoch
over every one of them costs many times what it teaches. An epoch draws ``per_epoch`` of them at
random without replacement instead: the early-stopping check then comes every ``per_epoch``
windows whatever the dataset's size, and a large dataset is not visited in full between checks.
"""

from __future__ import annotations

import numpy as np
import torch


def epoch_order(units: np.ndarray, per_epoch: int, gen: torch.Generator) -> np.ndarray:
    """One epoch's training units (window rows, or (S, steps) runs of rows) in random order.

    ``per_epoch`` 0, or at least ``len(units)``: every unit once (one permutation drawn from
    ``gen``); else ``per_epoch`` of them, drawn without replacement. Deterministic given ``gen``.
    """
    perm = torch.randperm(len(units), generator=gen).numpy()
    if 0 < per_epoch < len(units):
        perm = perm[:per_epoch]
    return units[perm]
