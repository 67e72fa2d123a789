"""Data-parallel training in several processes: one process per GPU (nccl) or per CPU share (gloo).

Every rank holds the same networks and takes the same global step on its own slice of the global
batch (data.BatchStream's shard); the gradients are averaged over the ranks before every optimiser
step, so all ranks apply identical updates and stay bit-identical to each other, and a step equals a
single-process step on the whole batch up to float rounding.

The average is one explicit all-reduce per update (`average_gradients`), not torch's
DistributedDataParallel wrapper, because of what WGAN-GP does: the critic update runs the critic three
times (real, fake, interpolates) and differentiates through a gradient (the penalty's double backward),
and the generator update runs the frozen critic; the wrapper's reducer expects every forward of the
wrapped module to be followed by one backward that reaches all its parameters, and misreports or hangs
otherwise. An explicit average after backward has no such rule, and lets the ranks agree on skipping a
non-finite step (`agree`) before anyone waits for the others' gradients.

`torchrun` describes a rank in RANK / WORLD_SIZE / LOCAL_RANK / MASTER_ADDR / MASTER_PORT (`join_from_env`);
`launch` starts N such processes on this machine itself (torch.multiprocessing.spawn), so that the
parent, the admc command, can name the rank that failed in one clear message.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch._utils import _flatten_dense_tensors, _unflatten_dense_tensors
from tqdm import tqdm

from admc.errors import AdmcError, DeviceError, TrainingError

if TYPE_CHECKING:
    from ..nets.settings import ModelSettings
    from ..train_settings import TrainSettings


class RankFailed(AdmcError, RuntimeError):
    """A training process died or lost contact with the others; the run stopped."""


@dataclass(frozen=True)
class Ranks:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1

    @property
    def lead(self) -> bool:
        """Rank 0 alone writes checkpoints, logs, weights and progress."""
        return self.rank == 0


def current() -> Ranks:
    """This process's place in the initialised process group (rank 0 of 1 without one)."""
    if not (dist.is_available() and dist.is_initialized()):
        return Ranks()
    return Ranks(
        dist.get_rank(),
        dist.get_world_size(),
        int(os.environ.get("LOCAL_RANK", "0")),
        int(os.environ.get("LOCAL_WORLD_SIZE", "1")),
    )


def backend_for(device: torch.device) -> str:
    return "nccl" if device.type == "cuda" else "gloo"


def join_from_env(device: torch.device) -> Ranks:
    """Join the process group that torchrun's environment describes (WORLD_SIZE > 1); rank 0 of 1 otherwise."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group(backend_for(device))
    return current()


def rank_device(device: torch.device, ranks: Ranks) -> torch.device:
    """One GPU per local rank; the CPU is shared."""
    if device.type == "cuda" and ranks.world > 1:
        return torch.device("cuda", ranks.local_rank)
    return device


@contextlib.contextmanager
def _collective():
    """A collective that fails raises RankFailed: another rank is gone (gloo raises a bare RuntimeError,
    nccl a DistBackendError, which is one too; the tensors are admc's own, so nothing else fails there)."""
    try:
        yield
    except RuntimeError as exc:
        ranks = current()
        said = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise RankFailed(
            f"training process rank {ranks.rank} of {ranks.world} lost contact with the others ({said})"
        ) from None


def agree(ok: bool, device: torch.device) -> bool:
    """True on every rank when `ok` is true on every rank: a step is skipped everywhere or nowhere."""
    if current().world == 1:
        return ok
    flag = torch.tensor([1 if ok else 0], device=device)
    with _collective():
        dist.all_reduce(flag, op=dist.ReduceOp.MIN)
    return bool(flag.item())


def average_gradients(params: list[torch.nn.Parameter]) -> None:
    """Replace each gradient by its mean over the ranks (one all-reduce of them all, float32)."""
    world = current().world
    grads = [p.grad for p in params if p.grad is not None]
    if world == 1 or not grads:
        return
    flat = _flatten_dense_tensors([g.contiguous() for g in grads])
    with _collective():
        dist.all_reduce(flat)
    flat /= world
    for grad, mean in zip(grads, _unflatten_dense_tensors(flat, grads)):
        grad.copy_(mean)


def average_values(values: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """Logged losses as the mean over the ranks (the loss of the whole global batch)."""
    if current().world == 1 or not values:
        return values
    keys = sorted(values)
    stacked = torch.stack([values[k].detach().float().to(device) for k in keys])
    with _collective():
        dist.all_reduce(stacked)
    return dict(zip(keys, stacked / current().world))


def broadcast_modules(*modules: torch.nn.Module) -> None:
    """Rank 0's parameters and buffers on every rank (they are equal already when seeded alike)."""
    if current().world == 1:
        return
    with _collective():
        for module in modules:
            for tensor in [*module.parameters(), *module.buffers()]:
                dist.broadcast(tensor.data, 0)


def share(obj: Any) -> Any:
    """Rank 0's `obj` on every rank."""
    if current().world == 1:
        return obj
    box = [obj]
    with _collective():
        dist.broadcast_object_list(box, 0)
    return box[0]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_main(rank: int, nproc: int, port: int, backend: str, fn: Callable, kwargs: dict, queue) -> None:
    """One launched rank: join the group, run fn; rank 0 sends back its result, a user error its message."""
    os.environ.update(
        {
            "MASTER_ADDR": "127.0.0.1",
            "MASTER_PORT": str(port),
            "RANK": str(rank),
            "WORLD_SIZE": str(nproc),
            "LOCAL_RANK": str(rank),
            "LOCAL_WORLD_SIZE": str(nproc),
        }
    )
    if backend == "nccl":
        torch.cuda.set_device(rank)
    # tqdm's default lock is a multiprocessing semaphore: one left by a killed rank makes Python warn of
    # "leaked semaphore objects" at exit, after admc's own message. A rank has one thread that prints.
    tqdm.set_lock(threading.RLock())
    dist.init_process_group(backend, rank=rank, world_size=nproc)
    try:
        result = fn(**kwargs)
    except AdmcError as exc:
        queue.put(("error", rank, exc))
        raise SystemExit(2) from None
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
    if rank == 0:
        queue.put(("result", rank, result))


def launch(nproc: int, device: torch.device, fn: Callable, kwargs: dict) -> Any:
    """fn(**kwargs) in `nproc` processes on this machine, joined in one process group; rank 0's result.

    A rank that stops with a user error (an AdmcError) ends them all and its error is raised here, a
    rank's own error before another's report of losing it; a rank that dies (a signal, an exit) is
    named in RankFailed. A bug in a rank keeps its traceback (torch's ProcessRaisedException)."""
    if device.type == "cuda" and nproc > torch.cuda.device_count():
        raise DeviceError(f"--nproc {nproc}: one process per GPU, but this machine has {torch.cuda.device_count()}")
    queue = mp.get_context("spawn").SimpleQueue()
    # torch logs a warning per rank it stops after a failure; RankFailed says what happened instead
    logging.getLogger("torch.multiprocessing.spawn").setLevel(logging.ERROR)
    try:
        mp.spawn(_rank_main, args=(nproc, _free_port(), backend_for(device), fn, kwargs, queue), nprocs=nproc)
    except mp.ProcessExitedException as exc:
        said = sorted((isinstance(e, RankFailed), rank, e) for kind, rank, e in _drain(queue) if kind == "error")
        if said and not exc.signal_name:
            raise said[0][2] from None
        how = f"was killed by {exc.signal_name}" if exc.signal_name else f"exited with code {exc.exit_code}"
        raise RankFailed(
            f"training process rank {exc.error_index} of {nproc} (pid {exc.error_pid}) {how}; "
            "the other ranks were stopped"
        ) from None
    results = [r for kind, _, r in _drain(queue) if kind == "result"]
    return results[0]


def _drain(queue) -> list[tuple]:
    items = []
    while not queue.empty():
        items.append(queue.get())
    return items


def check_world(settings: TrainSettings, model: ModelSettings, world: int) -> None:
    """What `world` training processes need: a global batch that splits evenly, and no batch norm in the
    critic (its statistics would cover each process's slice, not the batch one process normalises over)."""
    if settings.batch_size % world:
        raise TrainingError(
            f"config key 'train.batch_size': the global batch of {settings.batch_size} does not "
            f"split across {world} training processes; use a multiple of {world}"
        )
    if world > 1 and model.critic_norm == "batch":
        raise TrainingError(
            f"config key 'model.critic_norm': \"batch\" would normalise over each of the {world} "
            'training processes\' slices of the batch, not over the whole batch; use "layer" '
            '(the default) or "none", or train in one process'
        )
    if world > 1 and settings.oidn_minutes > 0 and model.base == "noisy":
        raise TrainingError(
            f"config key 'train.oidn_minutes': OIDN's fine-tune runs in one process, not {world}; "
            "train in one process, or set it to 0"
        )
