"""Data-parallel training through torchrun: W processes (ranks) share each step's rays and average their gradients.

    torchrun --nproc-per-node 2 -m nerfpipe.cli train SCENE RUN ...   # gloo on CPU, NCCL on GPUs

torchrun starts W copies of the same command with RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and MASTER_PORT set
(`world_from_env`); without them the command is one process and nothing here runs (`SINGLE`).

Global batch semantics: every rank draws the step's whole batch of B rays (and its per-ray random background
colours) from the same generator, so all ranks hold the same batch, and rank r renders its `World.share` of it:
rays [r B // W, (r + 1) B // W), contiguous, sizes differing by at most one. Each rank's loss is its per-ray terms
(means over its rays) weighted by n_r W / B plus the terms every rank computes alike (priors, the depth term's
rays); `DataParallel.average` sums the gradients over the ranks and divides by W, which gives the one-process
gradient of the whole batch up to the order of float summation. Every rank then takes the same optimiser step,
so the parameters stay identical on every rank without being sent.

Random numbers: the generator of the batch (`gen`: ray indices, background colours, TV texels, depth rays) is drawn
whole on every rank. The renderer's own draws (the march's jitter) come from torch's global generator inside
`model.render`; `DataParallel.share_draws` starts each rank at its share's place in that stream and leaves every
rank where one process drawing the whole batch would be. On CPU, torch's generator (mt19937) draws float32 values
one after another, so rank r's jitter is exactly the one process's jitter of its rays (tested); on CUDA (Philox:
where a value lands depends on the draw's size) and for the vanilla field (two draws a step), ranks get distinct
draws of the same distribution, not the one process's numbers.

Occupancy grid: not sent. Its update reads the field (identical on every rank), a generator seeded by the step and
torch's global generator (kept in step on every rank, above), so every rank computes the same grid. Broadcasting it
from rank 0 would cost little (64^3 floats every 16 steps), but it would hide a divergence of the parameters rather
than catch it: `DataParallel.check_same` compares a fingerprint of the parameters and the grid across ranks at the
start and at every checkpoint and stops the run naming what differs.

Decisions (stop, time budget, checkpoints): `DataParallel.agree`, once a step, takes any rank's stop signal, rank 0's
training seconds and rank 0's wall-clock checkpoint decision, so that every rank stops, changes its learning rate,
upsamples and checkpoints at the same step. Rank 0 is the one writer (checkpoints, metrics, the manifest).

Why not DistributedDataParallel: DDP wraps one module whose forward is the whole step; here a step renders through
a field, a background, appearance codes and camera corrections (their own optimiser), the fast field replaces its
parameters when the grid is upsampled (DDP would be rebuilt), and TV gradients are added after backward. One flat
all-reduce after backward does the same sum with nothing to re-wrap; what it gives up is DDP's overlap of the
reduction with backward (bucketed hooks), which matters once the reduction costs as much as the step.
"""

from __future__ import annotations

import contextlib
import datetime
import math
import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from nerfpipe.data.errors import UserError
from nerfpipe.model.device import resolve_device

__all__ = ["World", "SINGLE", "world_from_env", "rank_device", "DataParallel", "joined", "FINISH_WAIT"]

FINISH_WAIT = datetime.timedelta(hours=24)
"""How long the other ranks wait at the end of a run for rank 0's final evaluation and writes (`joined`): minutes in
practice; the bound only ends the wait of a rank whose writer hangs."""


@dataclass(frozen=True)
class World:
    """This process's place among the ranks of a run: rank in [0, size), local_rank on its machine."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0
    local_size: int = 1

    @property
    def writer(self) -> bool:
        """Rank 0 writes the run folder (checkpoints, metrics, manifest); the others only train."""
        return self.rank == 0

    def share(self, n: int) -> slice:
        """This rank's part of n items: [rank n // size, (rank + 1) n // size) (every item in exactly one part)."""
        return slice(self.rank * n // self.size, (self.rank + 1) * n // self.size)


SINGLE = World()
"""One process (no torchrun)."""

_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE")


def world_from_env(env: Mapping[str, str] | None = None) -> World:
    """The World torchrun describes in the environment; SINGLE without WORLD_SIZE (or with WORLD_SIZE=1)."""
    env = os.environ if env is None else env
    if "WORLD_SIZE" not in env:
        return SINGLE
    try:
        size = int(env["WORLD_SIZE"])
        rank, local = int(env.get("RANK", "0")), int(env.get("LOCAL_RANK", "0"))
        local_size = int(env.get("LOCAL_WORLD_SIZE", str(size)))
    except ValueError:
        got = ", ".join(f"{k}={env.get(k)!r}" for k in _ENV)
        raise UserError(f"expected whole numbers in {', '.join(_ENV)} (set by torchrun), got {got}") from None
    if size < 1 or not 0 <= rank < size or not 0 <= local < max(local_size, 1):
        raise UserError(
            f"expected 0 <= RANK < WORLD_SIZE and 0 <= LOCAL_RANK < LOCAL_WORLD_SIZE (set by "
            f"torchrun), got RANK={rank}, WORLD_SIZE={size}, LOCAL_RANK={local}, "
            f"LOCAL_WORLD_SIZE={local_size}"
        )
    return SINGLE if size == 1 else World(rank=rank, size=size, local_rank=local, local_size=local_size)


def rank_device(name: str, world: World) -> torch.device:
    """The device of this rank: `resolve_device`'s, and with several ranks "auto" or "cuda" (when CUDA is there)
    become cuda:LOCAL_RANK; "cuda:N" is refused when several ranks share this machine (they would share one GPU)."""
    if world.size == 1:
        return resolve_device(name)
    dev = resolve_device(name)
    if dev.type != "cuda":
        return dev
    if dev.index is not None and world.local_size > 1:
        raise UserError(
            f"device: {name} would put the {world.local_size} ranks of this machine on one GPU; give "
            "device cuda or auto (rank r takes cuda:LOCAL_RANK)"
        )
    index = world.local_rank if dev.index is None else dev.index
    if index >= torch.cuda.device_count():
        raise UserError(
            f"device: rank {world.rank} needs cuda:{index} (LOCAL_RANK), torch sees "
            f"{torch.cuda.device_count()} CUDA devices; start at most that many processes a "
            "machine"
        )
    return torch.device("cuda", index)


class DataParallel:
    """The collectives of one data-parallel run (module doc): built by `joined` inside an initialised group."""

    def __init__(self, world: World, device: torch.device, backend: str):
        self.world, self.device, self.backend = world, device, backend

    @property
    def writer(self) -> bool:
        return self.world.writer

    def describe(self) -> dict:
        """The manifest's `used.data_parallel`."""
        return {
            "world_size": self.world.size,
            "backend": self.backend,
            "rays": "each step's batch drawn whole "
            "on every rank; rank r renders rays [r B // W, (r + 1) B // W); gradients summed over the ranks "
            "and divided by W (the one-process gradient of the batch up to float summation order)",
        }

    def _all_reduce(self, t: Tensor, op: str = "sum") -> Tensor:
        import torch.distributed as dist

        ops = {"sum": dist.ReduceOp.SUM, "max": dist.ReduceOp.MAX}
        dist.all_reduce(t, op=ops[op])
        return t

    def announce(self, ok: bool | None = None) -> bool:
        """Rank 0 says whether it could take the run folder (ok); every rank returns what rank 0 said."""
        flag = torch.tensor([1.0 if (self.writer and ok) else 0.0], device=self.device)
        return bool(self._all_reduce(flag, "max")[0] > 0)

    def barrier(self) -> None:
        """Every rank has got here (rank 0 writes config.json only after every rank has read the run's files)."""
        self._all_reduce(torch.zeros(1, device=self.device))

    def agree(self, signum: int | None, seconds: float, wall_due: bool) -> tuple[int | None, float, bool]:
        """Once a step, on every rank: the largest stop signal any rank got (None: none did), rank 0's training
        seconds and rank 0's wall-clock checkpoint decision (`model.loop.TrainingLoop`)."""
        mine = [float(signum or 0), seconds if self.writer else -math.inf, 1.0 if (self.writer and wall_due) else 0.0]
        got = self._all_reduce(torch.tensor(mine, dtype=torch.float64, device=self.device), "max").tolist()
        return (int(got[0]) or None), got[1], got[2] > 0

    def average(self, params: Iterable[Tensor], extras: list[float]) -> list[float]:
        """Gradients of `params` summed over the ranks and divided by the world size, in place (a gradient that
        is None counts as zeros, and stays None only where it is None on every rank, as a one-process backward
        would leave it); `extras` summed over the ranks, returned."""
        params = list(params)
        if not params:
            return self._all_reduce(torch.tensor(extras, dtype=torch.float64, device=self.device)).tolist()
        like = params[0]
        flat = [
            p.grad.reshape(-1) if p.grad is not None else torch.zeros(p.numel(), dtype=p.dtype, device=p.device)
            for p in params
        ]
        present = [1.0 if p.grad is not None else 0.0 for p in params]
        tail = torch.tensor(present + list(extras), dtype=torch.float64, device=like.device)
        buf = torch.cat([f.to(torch.float32) for f in flat])
        buf = self._all_reduce(buf)
        tail = self._all_reduce(tail).tolist()
        buf /= self.world.size
        offset = 0
        for p, n_present in zip(params, tail[: len(params)], strict=True):
            part = buf[offset : offset + p.numel()].view_as(p).to(p.dtype)
            offset += p.numel()
            p.grad = part.clone() if n_present > 0 else None
        return tail[len(params) :]

    @contextlib.contextmanager
    def share_draws(self, total: int, share: slice, per_ray: int = 1) -> Iterator[None]:
        """Inside: torch's global generator of this rank's device placed where one process drawing `per_ray`
        float32 values for each of `total` rays would be at the first ray of `share`; after: where that process
        would be after all of them (module doc: exact on CPU, rank-distinct on CUDA)."""
        cuda = self.device.type == "cuda"
        get = (lambda: torch.cuda.get_rng_state(self.device)) if cuda else torch.get_rng_state
        state = get()
        try:
            if share.start:
                torch.rand(share.start * per_ray, device=self.device)
            yield
        finally:
            if cuda:
                torch.cuda.set_rng_state(state, self.device)
            else:
                torch.set_rng_state(state)
            torch.rand(total * per_ray, device=self.device)

    def check_same(self, named: Mapping[str, Tensor | None], where: str) -> None:
        """RuntimeError on every rank when a tensor differs between ranks (a float64 sum and sum of squares per
        tensor, compared by their largest and smallest value over the ranks)."""
        names = [k for k, v in named.items() if v is not None]
        if not names:
            return
        fp = (
            torch.stack(
                [
                    torch.stack([named[k].detach().double().sum(), named[k].detach().double().square().sum()])
                    for k in names
                ]
            )
            .reshape(-1)
            .to(self.device)
        )
        hi, lo = self._all_reduce(fp.clone(), "max"), -self._all_reduce(-fp, "max")
        differ = [names[i // 2] for i in torch.nonzero(~((hi == lo) | (hi.isnan() & lo.isnan())))[:, 0].tolist()]
        if differ:
            raise RuntimeError(
                f"data-parallel ranks diverged {where}: {', '.join(sorted(set(differ)))} differ between "
                "ranks (a nondeterministic operation on one rank?)"
            )


@contextlib.contextmanager
def joined(world: World, device: torch.device) -> Iterator[DataParallel]:
    """The process group of this rank (env://: torchrun's MASTER_ADDR and MASTER_PORT; NCCL on CUDA, gloo on
    CPU), destroyed on the way out. A block that ends without an exception ends at a barrier: every rank leaves
    when rank 0 has written the run's outputs. Without it the other ranks exited while rank 0 still evaluated and
    wrote, and torchrun ends the whole run when a rank's process ends badly: rarely (twice in some 300 two-rank CPU
    runs here) rank 1 aborted on its way out ("terminate called without an active exception", cause not found) and
    torchrun sent SIGTERM to rank 0 in the middle of its writes."""
    import torch.distributed as dist

    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    try:
        dist.init_process_group(backend, init_method="env://", rank=world.rank, world_size=world.size)
    except (ValueError, RuntimeError) as exc:
        raise UserError(
            f"cannot join the other {world.size - 1} ranks ({backend}: {str(exc).splitlines()[0]}); start "
            "the command with torchrun"
        ) from None
    try:
        yield DataParallel(world, device, backend)
        try:
            dist.barrier(timeout=FINISH_WAIT)
        except RuntimeError as exc:  # another rank ended with an error after training: its own line says why
            raise UserError(
                f"rank {world.rank}: another rank stopped before the end of the run (its message says "
                f"why; {backend}: {str(exc).splitlines()[0]})"
            ) from None
    finally:
        dist.destroy_process_group()
