"""Data-parallel training with PyTorch's own engine, or one process: the same calls.

``torchrun --nproc-per-node N [--nnodes M ...] -m tactile.training.commands.train DATA --out
RUN`` starts N processes per node; torchrun sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``,
``LOCAL_WORLD_SIZE`` and the rendezvous address, and :class:`Dist` reads them (as
pytorch/examples' ``multigpu_torchrun.py`` does). Without them it is one process and every
method is the identity. Backend: NCCL on GPUs, gloo on CPUs; tensors that live on the CPU
(features, statistics) travel over a gloo group in both cases.
"""

from __future__ import annotations

import gc
import math
import os
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.distributed as td
from torch import nn


@dataclass
class Dist:
    """This process's place in the job: ``rank`` of ``world`` processes, ``local_rank`` of the
    ``local_world`` on this node."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1
    _cpu_group: object = field(default=None, repr=False)
    _wrapped: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_env(cls) -> Dist:
        env = os.environ
        world = int(env.get("WORLD_SIZE", "1"))
        if world <= 1:
            return cls()
        return cls(int(env["RANK"]), world, int(env.get("LOCAL_RANK", "0")),
                   int(env.get("LOCAL_WORLD_SIZE", str(world))))

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def device(self, kind: str) -> torch.device:
        """The device of this process: its node's GPU ``local_rank`` for ``cuda``."""
        return torch.device("cuda", self.local_rank) if kind == "cuda" else torch.device("cpu")

    def start(self, device: torch.device) -> None:
        """Join the process group (NCCL on GPUs, gloo on CPUs); nothing for one process."""
        if self.world == 1 or td.is_initialized():
            return
        if device.type == "cuda":
            torch.cuda.set_device(device)
            td.init_process_group(backend="nccl")
            self._cpu_group = td.new_group(backend="gloo")
        else:
            td.init_process_group(backend="gloo")

    def finish(self) -> None:
        """Leave the process group together: the DDP wrappers freed first (their reducers
        hold the group, and reference cycles keep them until a collection: a group still alive
        when the interpreter exits can abort the process in gloo's threads), then a barrier,
        so that no process tears the group down while another still talks on it."""
        self._wrapped.clear()
        if self.world > 1 and td.is_initialized():
            gc.collect()
            td.barrier(group=self._cpu_group)
            td.destroy_process_group()

    # --- collectives on CPU tensors (identity for one process) ---------------------------------

    def barrier(self) -> None:
        """Wait until every process gets here."""
        if self.world > 1:
            td.barrier(group=self._cpu_group)

    def any(self, flag: bool) -> bool:
        """True on every process when ``flag`` is True on any (a Ctrl-C stops them all)."""
        if self.world == 1:
            return flag
        t = torch.tensor([int(flag)])
        td.all_reduce(t, op=td.ReduceOp.MAX, group=self._cpu_group)
        return bool(t.item())

    def sum(self, *values: float) -> tuple[float, ...]:
        """Each value summed over the processes."""
        if self.world == 1:
            return values
        t = torch.tensor(values, dtype=torch.float64)
        td.all_reduce(t, group=self._cpu_group)
        return tuple(t.tolist())

    def broadcast(self, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
        """Rank 0's arrays on every process (statistics fitted once, used by all)."""
        if self.world == 1:
            return arrays
        out = []
        for a in arrays:
            t = torch.from_numpy(np.ascontiguousarray(a)).clone()
            td.broadcast(t, src=0, group=self._cpu_group)
            out.append(t.numpy())
        return tuple(out)

    def sync_buffers(self, module: nn.Module) -> None:
        """Rank 0's buffers of ``module`` (batch norm's running statistics) on every process.
        DDP sends them at the start of each training step, so after the last step every
        process holds statistics updated by its own share of the batch: evaluated so, the
        processes would judge different models and could stop on different epochs."""
        if self.world == 1:
            return
        for buf in module.buffers():
            t = buf.detach().cpu().clone()
            td.broadcast(t, src=0, group=self._cpu_group)
            buf.data.copy_(t.to(buf.device))

    def slice(self, n: int) -> tuple[int, int]:
        """This process's contiguous share [lo, hi) of ``n`` rows (for :meth:`gather`)."""
        per = math.ceil(n / self.world)
        return min(n, self.rank * per), min(n, (self.rank + 1) * per)

    def gather(self, part: torch.Tensor, n: int) -> torch.Tensor:
        """Every process's :meth:`slice` of ``n`` rows, put together on every process."""
        if self.world == 1:
            return part
        per = math.ceil(n / self.world)
        padded = torch.zeros((per, *part.shape[1:]), dtype=part.dtype)
        padded[: len(part)] = part
        chunks = [torch.empty_like(padded) for _ in range(self.world)]
        td.all_gather(chunks, padded, group=self._cpu_group)
        return torch.cat(chunks)[:n]

    def shard(self, order: np.ndarray) -> np.ndarray:
        """This process's share of an epoch's order, as ``DistributedSampler`` makes it: padded
        by wrapping round to a multiple of ``world`` (every process then takes as many
        batches), then every ``world``-th item from ``rank``."""
        if self.world == 1:
            return order
        pad = (-len(order)) % self.world
        if pad:
            order = np.concatenate([order, order[:pad]])
        return order[self.rank :: self.world]

    def wrap(self, module: nn.Module, device: torch.device) -> nn.Module:
        """``module`` in DistributedDataParallel (gradients averaged over the processes at
        every backward pass; rank 0's weights broadcast when wrapped), one wrapper per module;
        ``module`` itself for one process."""
        if self.world == 1:
            return module
        if id(module) not in self._wrapped:
            ids = [device.index] if device.type == "cuda" else None
            self._wrapped[id(module)] = nn.parallel.DistributedDataParallel(module, device_ids=ids)
        return self._wrapped[id(module)]


__all__ = ["Dist"]
