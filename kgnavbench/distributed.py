"""Data-parallel training over torchrun's ranks (a helper of the runs and train stages; no stage).

    torchrun --standalone --nproc_per_node=2 -m kgnavbench train --method lstm_a3c ...

Each rank steps its own share of the agents (agent i of the run's list belongs to rank i mod
world_size) with its own generators, computes its losses, and the gradients are averaged over the
ranks (one all-reduce of all of them) before the clipping and the optimiser step, so every rank holds
the same weights after every update. The knowledge graph's co-visibility counts are summed over the
ranks, so the graph is the same everywhere too. Rank 0 alone writes config.json, metrics.csv and the
checkpoints; `last.pt` carries every rank's agents and generators, so a killed run resumes exactly
with the number of ranks it was started with (the run's config records `world_size`, so another
number is another run). Gloo on CPU (the backend torchrun gives a CPU job; NCCL where the tensors
live on a GPU). With one process nothing here does anything.

`KGNAVBENCH_CHECK_REPLICAS=1` makes every update compare a hash of every rank's weights (a check for
tests and for new code: it costs one small all-gather per update).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from datetime import timedelta

import torch
import torch.distributed as dist

from .errors import KgnavbenchError

CHECK_REPLICAS = "KGNAVBENCH_CHECK_REPLICAS"


@dataclass(frozen=True)
class Ranks:
    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        return self.rank == 0


SINGLE = Ranks()  # one process


RANK_TIMEOUT = "KGNAVBENCH_RANK_TIMEOUT"  # seconds the ranks wait for each other to join (default 300)


class DistributedError(KgnavbenchError, ValueError):
    """RANK / WORLD_SIZE that torchrun did not set, or set wrong, or ranks that never joined: one line."""


def from_env() -> Ranks:
    """This process's rank and the world size as torchrun sets them (1 process without torchrun). A
    stray or malformed RANK / WORLD_SIZE is a DistributedError, not a rank that silently does nothing."""
    rank, world = os.environ.get("RANK"), os.environ.get("WORLD_SIZE")
    if rank is None and world is None:
        return SINGLE
    try:
        r, w = int(rank if rank is not None else "0"), int(world if world is not None else "1")
    except ValueError:
        raise DistributedError(
            f"RANK={rank!r} and WORLD_SIZE={world!r} must be whole numbers (torchrun sets them; "
            "unset both for one process)"
        ) from None
    if not (w >= 1 and 0 <= r < w):
        raise DistributedError(
            f"RANK={r} is no rank of WORLD_SIZE={w} (0 <= RANK < WORLD_SIZE); unset both for one process"
        )
    if w > 1 and not os.environ.get("MASTER_ADDR"):
        raise DistributedError(
            f"WORLD_SIZE={w} without MASTER_ADDR: start the ranks with torchrun "
            "(or unset RANK and WORLD_SIZE)"
        )
    return Ranks(r, w)


def start(device: torch.device = torch.device("cpu")) -> Ranks:  # noqa: B008 - an immutable default
    """Join torchrun's process group (once): gloo on the CPU, NCCL for CUDA tensors; a single process
    joins nothing. Ranks that do not all join within KGNAVBENCH_RANK_TIMEOUT seconds (300) are a
    DistributedError, not torch's silent 30 minutes."""
    ranks = from_env()
    if ranks.world > 1 and not dist.is_initialized():
        try:
            seconds = float(os.environ.get(RANK_TIMEOUT, "300"))
        except ValueError:
            raise DistributedError(f"{RANK_TIMEOUT} must be a number of seconds") from None
        try:
            dist.init_process_group(
                "nccl" if device.type == "cuda" else "gloo", timeout=timedelta(seconds=seconds)
            )
        except (RuntimeError, dist.DistError) as e:
            raise DistributedError(
                f"rank {ranks.rank} of {ranks.world}: the ranks did not all join within {seconds:g} s "
                f"({type(e).__name__}); is every rank started (torchrun --nproc_per_node={ranks.world})?"
            ) from e
    return ranks


def average_gradients(parameters, ranks: Ranks) -> None:
    """Every parameter's gradient replaced by its mean over the ranks (a missing one counts as 0)."""
    if ranks.world == 1:
        return
    params = list(parameters)
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params])
    dist.all_reduce(flat)
    flat /= ranks.world
    offset = 0
    for p in params:
        n = p.numel()
        p.grad = flat[offset : offset + n].view_as(p).clone()
        offset += n


def sum_tensor(t: torch.Tensor, ranks: Ranks) -> torch.Tensor:
    """t summed over the ranks (in place; t itself with one process)."""
    if ranks.world > 1:
        dist.all_reduce(t)
    return t


def sum_numbers(values: dict[str, float], ranks: Ranks) -> dict[str, float]:
    """A dict of numbers summed over the ranks, key by key."""
    if ranks.world == 1:
        return values
    keys = sorted(values)
    t = sum_tensor(torch.tensor([float(values[k]) for k in keys], dtype=torch.float64), ranks)
    return dict(zip(keys, t.tolist()))


def gather(obj, ranks: Ranks) -> list | None:
    """Every rank's obj, in rank order, on rank 0 (None elsewhere); [obj] with one process."""
    if ranks.world == 1:
        return [obj]
    out = [None] * ranks.world if ranks.main else None
    dist.gather_object(obj, out, dst=0)
    return out


def check_replicas(parameters, ranks: Ranks, update: int) -> None:
    """With KGNAVBENCH_CHECK_REPLICAS=1: every rank's weights must be bit-identical (a RuntimeError)."""
    if ranks.world == 1 or os.environ.get(CHECK_REPLICAS) != "1":
        return
    digest = hashlib.sha256()
    for p in parameters:
        digest.update(p.detach().cpu().contiguous().numpy().tobytes())
    hashes = [None] * ranks.world
    dist.all_gather_object(hashes, digest.hexdigest())
    if len(set(hashes)) != 1:
        raise RuntimeError(f"the ranks' weights differ after update {update}: {hashes}")


def finish(ranks: Ranks) -> None:
    """Leave the process group once every rank got here."""
    if ranks.world > 1 and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()
