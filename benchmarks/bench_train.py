"""Print training throughput (patches/s) of one branch's full trainer step: critic update with
gradient penalty, then generator update (L1 + adversarial), optimiser steps and non-finite guards.

    .venv/bin/python benchmarks/bench_train.py [--device cpu|cuda] [--configs small paper]
        [--batch-size N] [--patch-size P] [--steps 5] [--threads N]

Inputs are random tensors in the store's value ranges (the data loader is not timed). CUDA runs
use the trainer's bf16 autocast and channels_last; timings are synchronised. Median over --steps
steps after two warm-up steps.
"""
from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

from admc.model.branch import BranchTrainer
from admc.model.settings import paper_settings, small_settings


def make_batch(batch_size: int, patch: int) -> dict[str, torch.Tensor]:
    return {"noisy": torch.rand(batch_size, 3, patch, patch) * 2,
            "features": torch.rand(batch_size, 7, patch, patch),
            "reference": torch.rand(batch_size, 3, patch, patch)}


def bench(name: str, device: torch.device, batch_size: int | None, patch: int, steps: int) -> None:
    model, train = paper_settings() if name == "paper" else small_settings()
    train = replace(train, batch_size=batch_size or train.batch_size, l1_warmup_steps=0, critic_only_steps=0,
                    critic_steps_per_g=1, head_tail_start_step=0)
    torch.manual_seed(0)
    trainer = BranchTrainer("diffuse", model, train, patch, device)
    batch = make_batch(train.batch_size, patch)

    def one_step() -> float:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        ok, _ = trainer.step(0, [batch])
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        if not ok:
            raise RuntimeError(f"{name}: benchmark step was skipped as non-finite")
        return time.perf_counter() - start

    for _ in range(2):
        one_step()
    seconds = statistics.median(one_step() for _ in range(steps))
    print(f"{name:6s} batch {train.batch_size:3d} patch {patch:4d}: {seconds * 1e3:9.1f} ms/step  "
          f"{train.batch_size / seconds:8.3g} patches/s per branch  (G + critic + GP, {device})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--configs", nargs="+", default=["small", "paper"], choices=("small", "paper"))
    parser.add_argument("--batch-size", type=int, default=None, help="default: each config's own")
    parser.add_argument("--patch-size", type=int, default=128)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--threads", type=int, default=0, help="CPU threads (0 = torch default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    for name in args.configs:
        bench(name, device, args.batch_size, args.patch_size, args.steps)


if __name__ == "__main__":
    main()
