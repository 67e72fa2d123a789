"""Print parameter counts, generator forward time and G + critic + GP training throughput.

    .venv/bin/python benchmarks/bench_model.py [--device cpu|cuda] [--repeats 3] [--threads N]

Times are medians over `--repeats` runs after one warm-up; CUDA timings are synchronised.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from admc.model.nets.critic import Critic
from admc.model.nets.generator import Generator
from admc.model.nets.losses import critic_loss, generator_loss
from admc.model.nets.settings import ModelSettings

MODELS = {
    "paper": ModelSettings(),
    "small": ModelSettings(channels=32, blocks=4, cond_channels=16, encoder_channels=32, critic_channels=16),
    "tiny": ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16, critic_channels=8),
}
PATCH_SIZES = {"paper": 128, "small": 64, "tiny": 32}
"""What each critic scores (the patch size fixes its linear layer)."""


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def median_seconds(fn, device: torch.device, repeats: int) -> float:
    def timed() -> float:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return time.perf_counter() - start

    timed()  # warm-up: allocator, kernel selection
    return statistics.median(timed() for _ in range(repeats))


def print_parameter_counts() -> None:
    print("parameters (generator per branch / critic):")
    for name, model in MODELS.items():
        g = Generator(model)
        critic = Critic(model, PATCH_SIZES[name])
        print(
            f"  {name:6s} generator {count(g):>11,d}  (encoder {count(g.encoder):,d})   critic {count(critic):>11,d}  "
            f"(critic_channels={model.critic_channels}, critic_norm={model.critic_norm!r}, patch {PATCH_SIZES[name]})"
        )
    for mode in ("none", "concat", "shift", "scale"):
        print(f"  paper generator, mode {mode:6s}: {count(Generator(ModelSettings(mode=mode))):>11,d}")


def bench_forward(device: torch.device, repeats: int, size: int = 256) -> None:
    noisy = torch.rand(1, 3, size, size, device=device)
    features = torch.rand(1, 7, size, size, device=device)
    for name in ("small", "paper"):
        g = Generator(MODELS[name]).to(device).eval()
        for layout in ("contiguous", "channels_last"):
            fmt = torch.channels_last if layout == "channels_last" else torch.contiguous_format
            g = g.to(memory_format=fmt)
            x, f = noisy.to(memory_format=fmt), features.to(memory_format=fmt)
            with torch.inference_mode():
                seconds = median_seconds(lambda: g(x, f), device, repeats)
            print(f"  generator {name:5s} forward {size}x{size} ({layout:13s}): {seconds * 1e3:9.1f} ms")


def bench_training(device: torch.device, repeats: int, name: str = "small", batch: int = 4) -> None:
    size = PATCH_SIZES[name]
    g = Generator(MODELS[name]).to(device)
    d = Critic(MODELS[name], size).to(device)
    opt_g = torch.optim.Adam(g.parameters(), 1e-4)
    opt_d = torch.optim.Adam(d.parameters(), 1e-4)
    noisy = torch.rand(batch, 3, size, size, device=device)
    features = torch.rand(batch, 7, size, size, device=device)
    clean = torch.rand(batch, 3, size, size, device=device)

    def step() -> None:
        fake = g(noisy, features)
        d_loss, _ = critic_loss(d, clean, fake)
        opt_d.zero_grad(set_to_none=True)
        d_loss.backward()
        opt_d.step()
        g_loss, _ = generator_loss(fake, clean, d(fake))
        opt_g.zero_grad(set_to_none=True)
        g_loss.backward()
        opt_g.step()

    seconds = median_seconds(step, device, repeats)
    print(
        f"  train step G+D+GP, {name} config, batch {batch} @ {size}x{size}: {seconds * 1e3:8.1f} ms "
        f"= {batch / seconds:7.1f} patches/s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=0, help="CPU intra-op threads (0: torch's default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    torch.manual_seed(0)
    print(f"torch {torch.__version__}, device {device}, threads {torch.get_num_threads()}")
    print_parameter_counts()
    print("timings (median of", args.repeats, "after one warm-up):")
    bench_forward(device, args.repeats)
    bench_training(device, args.repeats)
    if device.type == "cuda":
        bench_training(device, args.repeats, name="paper", batch=8)


if __name__ == "__main__":
    main()
