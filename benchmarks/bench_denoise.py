"""Print the full-image denoiser's time per image: both branches, random weights (speed does not
depend on them), paper and small generator configs; and, on the same image and device, the
baselines the evaluation compares against (Intel OIDN; NVIDIA OptiX where Mitsuba's CUDA variant runs).

    .venv/bin/python benchmarks/bench_denoise.py [--size 1280x720] [--configs paper small]
        [--baselines oidn optix] [--device cpu|cuda] [--tile 0] [--repeats 3] [--warmup 1]
        [--threads N] [--compile]

Each timed run is one FullImageDenoiser call; "network" is the generators' share (synchronised:
on CUDA it ends with the copy back to the host), "total" adds sanitising and the NumPy transforms.
Figures are medians over --repeats after --warmup untimed runs. --tile 0 runs the image in one
piece; a positive --tile runs it in tiles with the receptive-field halo. CUDA uses bfloat16
autocast and channels_last (the denoiser's defaults there).
"""
from __future__ import annotations

import argparse
import statistics

import numpy as np
import torch

from admc.model.denoiser import FullImageDenoiser, receptive_radius
from admc.model.generator import Generator, GeneratorConfig
from admc.pipeline.denoisers import OidnDenoiser, OptixDenoiser, optix_unavailable_reason, time_denoiser

CONFIGS = {
    "paper": GeneratorConfig(),
    "small": GeneratorConfig(channels=32, blocks=4, cond_channels=16, encoder_channels=32),
}


def synthetic_layers(height: int, width: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    normal = rng.normal(size=(height, width, 3)).astype(np.float32)
    return {
        "diffuse": rng.gamma(0.5, 2.0, size=(height, width, 3)).astype(np.float32),
        "specular": rng.gamma(0.3, 1.0, size=(height, width, 3)).astype(np.float32),
        "albedo": rng.random((height, width, 3), dtype=np.float32),
        "normal": normal / np.linalg.norm(normal, axis=-1, keepdims=True),
        "depth": rng.uniform(1.0, 20.0, size=(height, width, 1)).astype(np.float32),
        "coverage": np.ones((height, width, 1), dtype=np.float32),
    }


def bench(name: str, layers: dict[str, np.ndarray], args: argparse.Namespace) -> None:
    torch.manual_seed(0)
    diffuse, specular = Generator(CONFIGS[name]), Generator(CONFIGS[name])
    height, width = layers["diffuse"].shape[:2]
    tile = args.tile or max(height, width)
    denoiser = FullImageDenoiser(diffuse, specular, device=args.device, tile=tile, compile=args.compile)
    for _ in range(args.warmup):
        denoiser(layers)
    runs = [denoiser(layers) for _ in range(args.repeats)]
    network = statistics.median(r.network_seconds for r in runs) * 1e3
    total = statistics.median(r.seconds for r in runs) * 1e3
    print(f"{name:6s} {width}x{height} tile {tile} ({runs[0].tiles} per branch, halo {denoiser.overlap}, "
          f"receptive radius {receptive_radius(diffuse)}): network {network:9.1f} ms/image, "
          f"total {total:9.1f} ms/image  [{', '.join(runs[0].branches)}]", flush=True)


def bench_baseline(name: str, layers: dict[str, np.ndarray], args: argparse.Namespace) -> None:
    """The evaluation's own baselines, timed the way the evaluation times them (time_denoiser)."""
    height, width = layers["diffuse"].shape[:2]
    if name == "optix":
        reason = optix_unavailable_reason()
        if reason:
            print(f"optix  {width}x{height}: not run: {reason}", flush=True)
            return
        denoiser = OptixDenoiser()
    else:
        denoiser = OidnDenoiser(quality="high", device=args.device)
    _, seconds = time_denoiser(denoiser, layers, repeats=args.repeats, warmup=args.warmup)
    print(f"{name:6s} {width}x{height}: total {seconds * 1e3:9.1f} ms/image  [{denoiser.device}]", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--baselines", nargs="*", default=["oidn", "optix"], choices=["oidn", "optix"],
                        help="also time these on the same image (OIDN high quality on --device; OptiX on CUDA)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--tile", type=int, default=0, help="largest tile core edge; 0: no tiling")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--compile", action="store_true", help="torch.compile the generators")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.size.lower().split("x"))
    device = torch.device(args.device)
    where = (torch.cuda.get_device_name(device) if device.type == "cuda"
             else f"cpu, {torch.get_num_threads()} threads")
    print(f"torch {torch.__version__} on {where}; dtype {'bfloat16 autocast' if device.type == 'cuda' else 'float32'}"
          f"{', compiled' if args.compile else ''}; median of {args.repeats} after {args.warmup} warm-up")
    layers = synthetic_layers(height, width)
    for name in args.configs:
        bench(name, layers, args)
    for name in args.baselines:
        bench_baseline(name, layers, args)


if __name__ == "__main__":
    main()
