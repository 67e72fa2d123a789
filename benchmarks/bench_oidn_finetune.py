"""Print the speed of one step of OIDN's fine-tune (train.oidn_minutes): each branch's OIDN U-Net (diffuse with
albedo and normal, specular alone) on a batch of 128x128 patches, loss (train.oidn_loss) in OIDN's PU domain,
backward and Adam, in three forms side by side:

    .venv/bin/python benchmarks/bench_oidn_finetune.py [--batch-size 8] [--steps 5] [--warmup 2]
        [--loss l1|l1_msssim] [--threads N]

- `nchw float32`: the layout the fine-tune used before;
- `channels_last float32`: what it runs (model/training/oidn_partner.py);
- `channels_last bf16`: bf16 autocast, the form admc's own networks take on CPUs with fast bf16; faster there,
  but OIDN's networks trained so left 3-5% more HDR-FLIP on a product domain's test frames (3-9% on its val
  frames; docs/results/2026-12-06-fine-tuned-oidn.md), so the fine-tune does not use it. On a CPU without
  fast bf16 it is emulated and slow.

Inputs are random tensors in the networks' value ranges (the data loader is not timed); the forms take turns
step by step so a busy machine slows them alike; figures are medians over --steps, and the last line gives each
form's speed-up over the first. The step the partner takes counts both branches.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from admc.model.nets.losses import oidn_loss
from admc.model.nets.oidn_unet import INPUT_CHANNELS, oidn_unet
from admc.model.precision import MEMORY_FORMAT, autocast_for

FORMS = {
    "nchw float32": (torch.contiguous_format, torch.float32),
    "channels_last float32": (MEMORY_FORMAT, torch.float32),
    "channels_last bf16": (MEMORY_FORMAT, torch.bfloat16),
}


class Form:
    """One branch's network, optimiser and fixed batch in one layout and precision."""

    def __init__(self, branch: str, layout: torch.memory_format, dtype: torch.dtype, batch_size: int, loss: str):
        torch.manual_seed(0)
        self.net = oidn_unet(branch).to(memory_format=layout).train()
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=2e-5)
        self.x = torch.rand(batch_size, INPUT_CHANNELS[branch], 128, 128).contiguous(memory_format=layout)
        self.target = torch.rand(batch_size, 3, 128, 128)
        self.dtype, self.loss = dtype, loss

    def step(self) -> float:
        start = time.perf_counter()
        with autocast_for(torch.device("cpu"), self.dtype):
            output = self.net(self.x)
        loss = oidn_loss(output, self.target, self.loss)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch-size", type=int, default=8, help="train.batch_size of configs/domain.toml")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2, help="untimed steps per form first (>= 1)")
    parser.add_argument("--loss", default="l1", choices=("l1", "l1_msssim"))
    parser.add_argument("--threads", type=int, default=0, help="CPU threads (0 = torch default)")
    args = parser.parse_args()
    if args.warmup < 1 or args.steps < 1:
        parser.error("--warmup and --steps must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads; median of {args.steps} interleaved "
        f"steps after {args.warmup} warm-up; batch {args.batch_size} of 128x128, loss {args.loss}"
    )
    forms = {
        (name, branch): Form(branch, layout, dtype, args.batch_size, args.loss)
        for name, (layout, dtype) in FORMS.items()
        for branch in INPUT_CHANNELS
    }
    for form in forms.values():
        for _ in range(args.warmup):
            form.step()
    times = {key: [] for key in forms}
    for _ in range(args.steps):
        for key, form in forms.items():
            times[key].append(form.step())
    totals = {}
    for name in FORMS:
        per_branch = {b: statistics.median(times[(name, b)]) for b in INPUT_CHANNELS}
        totals[name] = sum(per_branch.values())
        branches = "  ".join(f"{b} {s * 1e3:7.1f} ms" for b, s in per_branch.items())
        print(f"{name:22s}: {branches}  partner step {totals[name]:.3f} s")
    base = next(iter(FORMS))
    print(f"speed-up over {base}: " + ", ".join(f"{n} {totals[base] / s:.2f}x" for n, s in totals.items() if n != base))


if __name__ == "__main__":
    main()
