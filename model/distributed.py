"""Where training runs: the device, and data parallelism across processes started by `torchrun`.

Under `torchrun` (WORLD_SIZE > 1) every process draws the same global batch from the same seeded generator and
trains on its own contiguous share of the rows; DistributedDataParallel averages the gradients. Losses are
normalised by the global batch's counts (`gmt.model.losses.gmt_loss(counts=...)`), so the shares add up to exactly
the loss of one process training on the whole batch: same curve, same checkpoint, up to float summation order.
Backend: gloo on CPU, NCCL on CUDA. Only rank 0 writes files.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import dataclass

import torch
import torch.distributed as dist


def resolve_device(device: str) -> torch.device:
    """`auto` -> cuda when available, else cpu; `cuda` without a GPU is an error naming the problem."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' was asked for, but torch sees no CUDA GPU (use --device auto or cpu)")
    return torch.device(device)


@dataclass
class Parallel:
    """This process's place in a (possibly one-process) training run.

    Attributes:
        rank: Index of this process (0 when not distributed).
        world: Number of processes.
        device: Device this process trains on.
    """

    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @classmethod
    def from_env(cls, device: str) -> Parallel:
        """Join the `torchrun` process group when WORLD_SIZE > 1, else a single process on `device`."""
        world = world_size()
        if world <= 1:
            return cls(0, 1, resolve_device(device))
        rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
        dev = resolve_device(device)
        if dev.type == "cuda":
            dev = torch.device("cuda", local)
            torch.cuda.set_device(dev)
        if not dist.is_initialized():
            dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
        return cls(rank, world, dev)

    @property
    def is_main(self) -> bool:
        """Whether this process writes files and prints."""
        return self.rank == 0

    def rows(self, batch_size: int) -> slice:
        """This process's share of a global batch of `batch_size` rows."""
        if batch_size % self.world:
            raise ValueError(f"batch_size {batch_size} must divide evenly over {self.world} processes")
        n = batch_size // self.world
        return slice(self.rank * n, (self.rank + 1) * n)

    def wrap(self, model: torch.nn.Module) -> torch.nn.Module:
        """The model as trained: DistributedDataParallel across processes, else itself."""
        if self.world == 1:
            return model
        from torch.nn.parallel import DistributedDataParallel

        ids = [self.device.index] if self.device.type == "cuda" else None
        return DistributedDataParallel(model, device_ids=ids)

    def sum(self, values: list[float]) -> list[float]:
        """Element-wise sum of `values` over every process (itself when alone)."""
        if self.world == 1:
            return values
        t = torch.tensor(values, dtype=torch.float64)
        dist.all_reduce(t)
        return t.tolist()

    def close(self) -> None:
        """Wait for every process, then leave the group (a `torchrun` worker then ends with `exit_worker`)."""
        if self.world > 1 and dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()


def world_size() -> int:
    """How many processes `torchrun` started for this run (its WORLD_SIZE; 1 without it)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def launched_by_torchrun() -> bool:
    """Whether this process is one of several that `torchrun` started (WORLD_SIZE > 1)."""
    return world_size() > 1


def exit_worker() -> None:
    """End a `torchrun` worker now (exit status 0), without the interpreter's shutdown; call it once every file is
    written and closed.

    The gloo process group's worker threads outlive `destroy_process_group` (the group stays referenced until
    exit), and one may still hold the last collective's tensors, which Python can see: dropping them takes the GIL
    (torch >= 2.10). If the interpreter has begun shutting down by then, the thread is unwound while taking it and
    the process aborts ("terminate called without an active exception", SIGABRT; 2 runs in 40 of the DDP test's
    run on a loaded 2-core machine, from a core dump: `AsyncBarrierWork` destroyed in `ProcessGroupGloo::runLoop`
    during `Py_FinalizeEx`). Skipping the shutdown leaves nothing to race with.
    """
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
