"""bench/baselines.py's judging of stopping rules: the epoch each rule keeps and its score on
held-out halves of the validation takes, on curves made by hand."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
from conftest import REPO


def _bench():
    spec = importlib.util.spec_from_file_location("baselines", REPO / "bench" / "baselines.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_halves_split_every_take_in_time():
    b = _bench()
    take = np.array([0, 0, 0, 0, 1, 1, 1])
    start = np.array([30, 0, 20, 10, 5, 0, 10])
    assert b._halves(take, start).tolist() == [False, True, False, True, False, True, False]


def test_pick_epoch_follows_the_rules_and_the_patience():
    b = _bench()
    acc = np.array([0.5, 0.6, 0.7, 0.8, 0.8, 0.7])
    loss = np.array([1.0, 0.8, 0.9, 1.2, 1.1, 1.5])
    assert b.pick_epoch("loss", acc, loss, patience=5) == 1
    assert b.pick_epoch("accuracy", acc, loss, patience=5) == 4  # the tie: the lower loss
    late = np.array([0.5, 0.6, 0.55, 0.8])  # a better epoch after one that is not
    assert b.pick_epoch("accuracy", late, loss[:4], patience=1) == 1
    assert b.pick_epoch("accuracy", late, loss[:4], patience=2) == 3


def test_rules_are_scored_on_the_half_they_did_not_pick_on(tmp_path):
    b = _bench()
    # 2 takes x 4 windows, 2 classes, 2 epochs; q: the probability of the right class. Epoch 0:
    # half the windows of each half-take sure and right (0.95), half wrong (0.45): accuracy
    # 0.5, loss 0.43; epoch 1: all barely right (0.55): accuracy 1, loss 0.60
    y = np.array([0, 1, 0, 1, 1, 0, 1, 0])
    take = np.repeat([0, 1], 4)
    start = np.tile([0, 1, 2, 3], 2)
    q = np.array([np.where(start % 2 == 0, 0.95, 0.45), np.full(8, 0.55)])
    probs = np.zeros((2, 8, 2))
    rows = np.arange(8)
    probs[:, rows, y] = q
    probs[:, rows, 1 - y] = 1 - q
    np.savez(tmp_path / "c.npz", probs=probs, y=y, take=take, start=start)
    r = b.selection_rules(tmp_path / "c.npz", patience=5)
    # on either half the loss keeps epoch 0 (0.5 on the other half), the accuracy epoch 1 (1.0)
    assert r["loss"] == {"held_out": 0.5, "epoch": 1, "val_accuracy": 0.5}
    assert r["accuracy"] == {"held_out": 1.0, "epoch": 2, "val_accuracy": 1.0}
