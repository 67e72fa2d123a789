"""Training data: a reproducible, resumable stream of augmented patch batches from a patch store.

The sample order and each sample's augmentation are a pure function of (seed, branch, position in
the stream), drawn in the main process: the data a run sees does not depend on the number of
workers or their scheduling, and a resumed run continues the stream by starting at the number of
batches it had consumed. Augmentation is the 8 symmetries of the square (symmetry.py).
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Iterator

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from admc.stores.patches import PatchReader

from ..symmetry import N_SYMMETRIES, apply

IMAGE_KEYS = ("noisy", "features", "reference", "base", "raw_reference")
"""The image entries of an item or batch ("base" only from a reader opened with a base, "raw_reference" only from
one with_raw_references())."""


class PatchDataset(Dataset):
    """Items are (row, augmentation code) pairs -> {"noisy", "features", "reference"[, "base", "raw_reference"]}
    float32 tensors, every image under the same symmetry.

    The PatchReader pickles without open zarr handles, so each DataLoader worker opens its own.
    """

    def __init__(self, reader: PatchReader):
        self.reader = reader

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, key: tuple[int, int]) -> dict[str, torch.Tensor]:
        row, code = key
        item = self.reader[row]
        return {
            name: apply(torch.from_numpy(item[name]), code, normals=name == "features").contiguous()
            for name in IMAGE_KEYS
            if name in item
        }


class BatchStream:
    """Endless batches of (row, augmentation) pairs: epochs of seeded permutations, batches taken
    across epoch boundaries. Batch b is the same for every run with the same (seed, n_rows, batch_size).

    With `shard` = (rank, world), this rank gets only its slice of each (global) batch: rank r's
    batch_size / world consecutive pairs. The ranks together see exactly the single-process stream,
    each reading only its own rows, and a resumed rank continues it at the same global batch.
    """

    def __init__(
        self,
        n_rows: int,
        batch_size: int,
        seed: int,
        start_batch: int = 0,
        augment: bool = True,
        shard: tuple[int, int] = (0, 1),
    ):
        if n_rows < 1:
            raise ValueError("BatchStream: no rows to sample")
        rank, world = shard
        if batch_size % world or not 0 <= rank < world:
            raise ValueError(f"BatchStream: a batch of {batch_size} has no shard {rank} of {world}")
        self.n_rows, self.batch_size, self.seed = n_rows, batch_size, seed
        self.start_batch, self.augment = start_batch, augment
        per_rank = batch_size // world
        self.slice = slice(rank * per_rank, (rank + 1) * per_rank)

    def _epoch(self, epoch: int) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng([self.seed, epoch])
        order = rng.permutation(self.n_rows)
        codes = rng.integers(0, N_SYMMETRIES, self.n_rows) if self.augment else np.zeros(self.n_rows, int)
        return order, codes

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        position = self.start_batch * self.batch_size
        epoch, offset = divmod(position, self.n_rows)
        order, codes = self._epoch(epoch)
        while True:
            batch = []
            while len(batch) < self.batch_size:
                if offset == self.n_rows:
                    epoch, offset = epoch + 1, 0
                    order, codes = self._epoch(epoch)
                batch.append((int(order[offset]), int(codes[offset])))
                offset += 1
            yield batch[self.slice]


def branch_seed(seed: int, branch: str) -> int:
    """Distinct, stable stream seeds per branch."""
    return seed * 2 + (1 if branch == "specular" else 0)


def train_loader(
    reader: PatchReader,
    batch_size: int,
    seed: int,
    start_batch: int = 0,
    num_workers: int = 0,
    pin_memory: bool = False,
    shard: tuple[int, int] = (0, 1),
) -> DataLoader:
    """An endless DataLoader over the reader, starting at batch `start_batch` of the seeded stream
    (this rank's `shard` of each batch under data-parallel training).

    The loader gets its own torch.Generator, so creating its iterator does not consume the global
    torch RNG (which the gradient penalty uses): a resumed run stays bit-identical.
    """
    stream = BatchStream(len(reader), batch_size, seed, start_batch, shard=shard)
    return DataLoader(
        PatchDataset(reader),
        batch_sampler=stream,
        num_workers=num_workers,
        pin_memory=pin_memory,
        persistent_workers=False,
        generator=torch.Generator().manual_seed(seed),
        prefetch_factor=2 if num_workers > 0 else None,
        worker_init_fn=loader_worker_init,
    )


def loader_worker_init(_worker_id: int) -> None:
    """In a loader worker: Ctrl-C is left to the main process, and a closed pipe prints nothing.

    Ctrl-C reaches every process of the terminal's group. The main process answers it with one line
    and shuts its loaders down (torch stops their workers); a worker that took it too would only race
    that shutdown. A worker hands each batch's tensors to the main process through file descriptors,
    served by multiprocessing's resource_sharer thread; when the main process stops reading mid-batch
    (Ctrl-C, or an error it reports itself), that thread meets a broken pipe and hands it to
    sys.excepthook, whose traceback would land under the CLI's message. Any other error prints as before.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    quiet_closed_pipes()


def quiet_closed_pipes() -> None:
    """sys.excepthook, as resource_sharer calls it, prints nothing for a broken or reset pipe."""
    previous = sys.excepthook

    def hook(exc_type, exc, tb) -> None:
        if not issubclass(exc_type, (BrokenPipeError, ConnectionResetError)):
            previous(exc_type, exc, tb)

    sys.excepthook = hook


def spread_rows(length: int, n: int) -> list[int]:
    """min(n, length) row indices evenly spaced over 0..length-1, first and last included.

    Rows are stored scene by scene, so the first n rows of a large split are one or two scenes;
    evenly spaced rows take from every scene once n reaches the number of scenes.
    """
    count = min(n, length)
    if count <= 1:
        return list(range(count))
    return [round(k * (length - 1) / (count - 1)) for k in range(count)]


def load_rows(reader: PatchReader, n: int) -> dict[str, torch.Tensor]:
    """min(n, len) rows spread evenly over the split (spread_rows), unaugmented, stacked: a fixed
    validation set."""
    if len(reader) == 0:
        raise ValueError(f"{reader.path}: split {reader.split!r} has no {reader.branch} patches")
    items = [reader[i] for i in spread_rows(len(reader), n)]
    return {key: torch.from_numpy(np.stack([item[key] for item in items])) for key in IMAGE_KEYS if key in items[0]}
