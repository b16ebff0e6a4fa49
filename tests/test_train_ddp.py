"""Data-parallel training: ``torchrun`` with 2 processes on loopback (gloo), then export.

Checks that the two processes learn (well above chance on users never seen in training), that
rank 0 alone prints and writes, that the normalisation is the training split's (fitted once),
and that the checkpoint is an ordinary one: ``load_checkpoint`` and ``tactile-export`` take it.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch

from tactile.device.recordings import load_dataset
from tactile.device.sim import TEXTURES, make_dataset
from tactile.training.checkpoint import load_checkpoint
from tactile.training.config import TrainConfig
from tactile.training.data import channel_stats, classes_of, cut, split_takes

EASY = ("non_contact", "paper", "nonwoven_cloth")
SETS = dict(epochs=6, hidden=24, layers=1, batch_size=64, lr=1e-2, patience=6, seed=3)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_learn_and_their_checkpoint_exports(tmp_path):
    data, run = tmp_path / "sim", tmp_path / "run"
    make_dataset(data, takes=6, textures=EASY, seconds=12, seed=1)
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2",
           "--master-addr", "127.0.0.1", "--master-port", str(free_port()),
           "-m", "tactile.training.commands.train", str(data), "--out", str(run),
           *(f"--set={k}={v}" for k, v in SETS.items())]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count("per take (majority vote)") == 1  # rank 0 alone prints
    assert proc.stderr.count("2 processes in all") == 1
    model, ck = load_checkpoint(run)
    m = ck["metrics"]
    assert m["processes"] == 2
    assert m["accuracy"] >= 0.6, m["accuracy"]  # 3 classes: chance is 1/3
    assert sorted(p.name for p in run.iterdir()) == [
        "checkpoint.pt", "confusion.png", "confusion.txt", "curves.png", "metrics.json"]
    # the same keys as a one-process run's model: no DDP "module." prefixes
    assert set(ck["state_dict"]) == set(model.state_dict())
    # normalisation: the statistics of the whole training split (not of one process's share)
    takes = load_dataset(data)
    cfg = TrainConfig(**SETS)
    train_w = cut(takes, classes_of(takes), (), cfg.window, cfg.hop, split_takes(takes, cfg).train)
    mean, std = channel_stats(train_w)
    np.testing.assert_allclose(ck["mean"], mean, rtol=1e-6)
    np.testing.assert_allclose(ck["std"], std, rtol=1e-6)
    pytest.importorskip("onnxruntime")
    from tactile.export.commands.export import main as export_main

    assert export_main([str(run), "-o", str(tmp_path / "m.onnx"), "--data", str(data)]) == 0
    assert (tmp_path / "m.onnx").stat().st_size > 1000
    assert torch.load(run / "checkpoint.pt", weights_only=True)["format"] == "tactile-checkpoint"


def _buffers_worker(rank: int, init: str, out: str) -> None:
    import torch.distributed as td

    from tactile.training.dist import Dist

    td.init_process_group("gloo", init_method=init, rank=rank, world_size=2)
    dist = Dist(rank=rank, world=2)
    norm = torch.nn.BatchNorm1d(3)
    norm.train()
    norm(torch.randn(16, 3, generator=torch.Generator().manual_seed(rank)) * (rank + 1))
    dist.sync_buffers(norm)
    metrics = dist.broadcast(np.array([0.5 + rank, 0.25 * rank]))[0]  # rank 0's on both
    torch.save({"buffers": [b.clone() for b in norm.buffers()], "metrics": metrics},
               f"{out}/rank{rank}.pt")
    dist.finish()


def test_every_process_judges_rank_0s_model(tmp_path):
    """After a training step each process's batch norm holds statistics of its own share of
    the batch; validation syncs rank 0's to all, so that all judge one model and keep the same
    best epoch (else one process could stop or refit for another count of epochs and leave
    the other waiting for ever in a collective)."""
    import torch.multiprocessing as mp

    init = f"file://{tmp_path / 'rendezvous'}"
    mp.start_processes(_buffers_worker, args=(init, str(tmp_path)), nprocs=2, join=True,
                       start_method="spawn")
    got = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in (0, 1)]
    for a, b in zip(got[0]["buffers"], got[1]["buffers"], strict=True):
        assert torch.equal(a, b)
    assert float(got[0]["buffers"][0].abs().sum()) > 0  # statistics, not untouched zeros
    np.testing.assert_array_equal(got[1]["metrics"], [0.5, 0.0])


def test_two_processes_agree_on_the_refit_length(tmp_path):
    """The best epoch, and so the refit's epoch count, is decided alike in both processes: the
    run ends, no process left waiting in a collective. (On this data the processes' own batch
    norm statistics once made them pick different best epochs, and the run never ended.)"""
    data, run = tmp_path / "sim", tmp_path / "run"
    make_dataset(data, takes=6, textures=TEXTURES, seconds=60, seed=0)  # the bench's small set
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2",
           "--master-addr", "127.0.0.1", "--master-port", str(free_port()),
           "-m", "tactile.training.commands.train", str(data), "--out", str(run), "--quiet",
           "--set=epochs=40", "--set=patience=50"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    m = load_checkpoint(run)[1]["metrics"]
    assert m["epochs_run"] == 40 and m["refit_epochs"] == m["best_epoch"] + 1, m
