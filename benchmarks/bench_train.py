"""Print training throughput (patches/s) of one branch's full trainer step in float32 and bf16 side by
side: critic update with gradient penalty, then generator update (L1 + adversarial), optimiser steps
and non-finite guards.

    .venv/bin/python benchmarks/bench_train.py [--device cpu|cuda] [--configs small paper small-unet]
        [--precisions float32 bfloat16] [--batch-size N] [--patch-size P] [--steps 5] [--warmup 2]
        [--threads N] [--compile] [--l1-only] [--ssim-weight W]

small and paper are the [model]/[train] of configs/default.toml and configs/paper.toml, small-unet the
small model on the multi-scale body (model.backbone = "unet"). Inputs are
random tensors in the store's value ranges (the data loader is not timed). One trainer per precision
(train.precision: bf16 autocast, float32 losses and gradient penalty; channels_last in both); after --warmup
steps each, the precisions take turns step by step, so a busy machine slows them alike; figures are
medians over --steps, and the last line gives each precision's speed-up over the first. --compile
wraps each generator in torch.compile (the critic's double backward for the penalty cannot be
compiled) and prints the first step, which pays the compilation. --l1-only times the step without a
critic (train.adversarial = false), the way the shipped weights' last runs trained; --ssim-weight adds the
SSIM term of the loss (train.ssim_weight). Timings are
synchronised on CUDA.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace
from importlib import resources

import torch

from admc.model.training.branch import BranchTrainer
from admc.pipeline.config import load_config


def make_batch(batch_size: int, patch: int) -> dict[str, torch.Tensor]:
    return {
        "noisy": torch.rand(batch_size, 3, patch, patch) * 2,
        "features": torch.rand(batch_size, 7, patch, patch),
        "reference": torch.rand(batch_size, 3, patch, patch),
    }


def timed_step(trainer: BranchTrainer, batch: dict[str, torch.Tensor], device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    ok, _ = trainer.step(0, [batch])
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    if not ok:
        raise RuntimeError(f"{trainer.settings.precision}: benchmark step was skipped as non-finite")
    return time.perf_counter() - start


def small_settings():
    """configs/default.toml's [model] and [train]: the small CPU model."""
    cfg = load_config()
    return cfg.model, cfg.train


def paper_settings():
    """configs/paper.toml's [model] and [train]: the paper's scale."""
    cfg = load_config(resources.files("admc.configs").joinpath("paper.toml"))
    return cfg.model, cfg.train


def small_unet_settings():
    """The small model on the multi-scale body (model.backbone = "unet"), same training settings."""
    model, train = small_settings()
    return replace(model, backbone="unet"), train


CONFIGS = {"small": small_settings, "paper": paper_settings, "small-unet": small_unet_settings}


def bench(name: str, device: torch.device, args: argparse.Namespace) -> None:
    model, train = CONFIGS[name]()
    train = replace(
        train,
        batch_size=args.batch_size or train.batch_size,
        l1_warmup_steps=0,
        critic_only_steps=0,
        critic_steps_per_g=1,
        head_tail_start_step=0,
        adversarial=not args.l1_only,
        ssim_weight=args.ssim_weight,
    )
    batch = make_batch(train.batch_size, args.patch_size)
    trainers = {}
    for precision in args.precisions:
        torch.manual_seed(0)
        trainers[precision] = BranchTrainer(
            "diffuse", model, replace(train, precision=precision), args.patch_size, device
        )
        if args.compile:
            trainers[precision].generator = torch.compile(trainers[precision].generator)
        try:
            first = timed_step(trainers[precision], batch, device)
        except Exception as error:  # torch.compile fails in many exception types
            if not args.compile:
                raise
            raise SystemExit(
                f"{name} {precision}: torch {torch.__version__} could not compile the training step: "
                f"{type(error).__name__}: {str(error).splitlines()[0]}"
            ) from None
        for _ in range(args.warmup - 1):
            timed_step(trainers[precision], batch, device)
        if args.compile:
            print(f"{name:6s} {precision:8s}: first (compiling) step {first:.1f} s", flush=True)
    times = {p: [] for p in trainers}
    for _ in range(args.steps):
        for precision, trainer in trainers.items():
            times[precision].append(timed_step(trainer, batch, device))
    medians = {p: statistics.median(t) for p, t in times.items()}
    step = ("G, L1 only" if args.l1_only else "G + critic + GP") + (" + SSIM" if args.ssim_weight else "")
    for precision, seconds in medians.items():
        print(
            f"{name:6s} {precision:8s} batch {train.batch_size:3d} patch {args.patch_size:4d}: "
            f"{seconds * 1e3:9.1f} ms/step  {train.batch_size / seconds:8.3g} patches/s per branch  "
            f"({step}, {device}{', compiled G' if args.compile else ''})",
            flush=True,
        )
    base = args.precisions[0]
    print(
        f"{name:6s} speed-up over {base}: "
        + ", ".join(f"{p} {medians[base] / s:.2f}x" for p, s in medians.items() if p != base),
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--configs", nargs="+", default=["small", "paper"], choices=list(CONFIGS))
    parser.add_argument("--precisions", nargs="+", default=["float32", "bfloat16"], choices=("float32", "bfloat16"))
    parser.add_argument("--batch-size", type=int, default=None, help="default: each config's own")
    parser.add_argument("--patch-size", type=int, default=128)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps per precision first (>= 1)")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads (0 = torch default)")
    parser.add_argument("--compile", action="store_true", help="torch.compile the generators")
    parser.add_argument("--l1-only", action="store_true", help="no critic: train.adversarial = false")
    parser.add_argument("--ssim-weight", type=float, default=0.0, help="train.ssim_weight (the SSIM loss term)")
    args = parser.parse_args()
    if args.warmup < 1:
        parser.error("--warmup must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads; median of {args.steps} interleaved "
        f"steps after {args.warmup} warm-up"
    )
    for name in args.configs:
        bench(name, device, args)


if __name__ == "__main__":
    main()
