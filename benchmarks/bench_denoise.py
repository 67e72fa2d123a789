"""Print the full-image denoiser's time per image in every engine and precision side by side: both
branches, random weights (speed does not depend on them), the paper's and the default (small) generator;
and, on the same image and device, the baselines the evaluation compares against (Intel OIDN; NVIDIA
OptiX where Mitsuba's CUDA variant runs), with each admc figure's ratio to OIDN. Last, for the default
engine (eval.engine of configs/default.toml) in its default precision, the lines
`admc/oidn time ratio: X` (small) and `admc+oidn/oidn time ratio: X` (small+oidn) against OIDN `high`.

    .venv/bin/python benchmarks/bench_denoise.py [--size 1280x720]
        [--configs paper small small+oidn small-slim small-unet]
        [--engines torch onnxruntime openvino] [--precisions float32 bfloat16] [--baselines oidn optix]
        [--device cpu|cuda] [--tile N] [--repeats 3] [--warmup 1] [--threads N] [--compile]

small and paper are the [model] of configs/default.toml and configs/paper.toml; small+oidn is the small
admc+oidn refiner on the default bases (tile.refiner_base), whose call runs OIDN per branch first;
small-slim is the small model with one CFM layer per residual block and one-layer condition nets
(model.cfm_per_block = model.condition_layers = 1); small-unet is the small model on the multi-scale body
(model.backbone = "unet"), whose tiles need a 116-px halo. Each timed run is one FullImageDenoiser call
(eval.keep_resolved as configs/default.toml sets it); "network" is the generators' share (synchronised: on
CUDA it ends with the copy back to the host), "total" adds sanitising and the log transforms. After --warmup
untimed runs each, the precisions and the baselines take turns run by run (a busy machine slows them alike);
figures are medians over --repeats. bfloat16 is autocast in torch and INFERENCE_PRECISION_HINT in OpenVINO
(the default on CUDA and on CPUs with AVX512-BF16 or AMX); ONNX Runtime runs float32 only, and the ONNX
engines run on a CPU only (model/inference/engines.py). By default the image runs in the denoiser's own
tiles with the receptive-field halo (tiling.default_tile: 320 on a CPU, 640 in OpenVINO, 512 on a GPU, at
least 8 halos), as `admc-pipe denoise` and eval do; --tile N sets the core edge, --tile 0 runs it in one
piece, which on a 2-core CPU is about twice as slow at 1280x720 in torch (whole-image convs leave the
caches) and within the run-to-run spread of tiles of 640 in OpenVINO (docs/engines.md).
"""

from __future__ import annotations

import argparse
import copy
import statistics
from dataclasses import replace
from importlib import resources

import admc  # noqa: F401  (first: it sets GOMP_SPINCOUNT before torch loads, as in admc-pipe)
import numpy as np
import torch

from admc.common.layout import ENGINES
from admc.model.inference.denoiser import FullImageDenoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.engines import default_precision, resolve_engine
from admc.model.inference.tiling import receptive_radius
from admc.model.nets.backbones import build_generator
from admc.model.precision import PRECISIONS, precision_name
from admc.pipeline.config import load_config
from admc.pipeline.evaluation.baselines import (
    Denoiser,
    OidnDenoiser,
    OptixDenoiser,
    optix_unavailable_reason,
    time_denoiser,
)

DEFAULTS = load_config()  # configs/default.toml
SMALL = DEFAULTS.model
CONFIGS = {
    "paper": load_config(resources.files("admc.configs").joinpath("paper.toml")).model,
    "small": SMALL,
    "small+oidn": replace(SMALL, base=DEFAULTS.tile.refiner_base),
    "small-slim": replace(SMALL, cfm_per_block=1, condition_layers=1),
    "small-unet": replace(SMALL, backbone="unet"),
}


RATIO_LINES = {"small": "admc/oidn", "small+oidn": "admc+oidn/oidn"}
"""The default model's two bases and the label of their time ratio to OIDN."""


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
        "diffuse_var": rng.gamma(0.5, 0.5, size=(height, width, 3)).astype(np.float32),  # for model.noise_input
        "specular_var": rng.gamma(0.3, 0.3, size=(height, width, 3)).astype(np.float32),
    }


def runs_here(engine: str, precision: str, device: str) -> bool:
    """Whether `engine` runs in `precision` on `device` (model/engines.check_engine's rules)."""
    if engine == "torch":
        return True
    return device == "cpu" and (engine == "openvino" or precision == "float32")


def bench(
    name: str, layers: dict[str, np.ndarray], baselines: dict[str, Denoiser], args: argparse.Namespace
) -> dict[str, float]:
    """Time admc (both branches) in each engine and precision and the baselines, taking turns run by run;
    returns the median total seconds per "engine precision" and per baseline."""
    torch.manual_seed(0)
    diffuse, specular = build_generator(CONFIGS[name]), build_generator(CONFIGS[name])
    height, width = layers["diffuse"].shape[:2]
    tile = max(height, width) if args.tile == 0 else args.tile
    # a copy of the networks per denoiser: it moves them to its memory layout in place
    denoisers = {
        f"{e} {p}": FullImageDenoiser(
            copy.deepcopy(diffuse),
            copy.deepcopy(specular),
            DenoiserOptions(
                device=args.device,
                tile=tile,
                dtype=PRECISIONS[p],
                compile=args.compile and e == "torch",
                engine=e,
                keep_resolved=DEFAULTS.eval.keep_resolved,
            ),
        )
        for e in args.engines
        for p in args.precisions
        if runs_here(e, p, args.device)
    }
    for precision, denoiser in denoisers.items():
        first = denoiser(layers).seconds
        for _ in range(args.warmup - 1):
            denoiser(layers)
        if args.compile:
            print(f"{name:6s} {precision:8s}: first (compiling) run {first:.1f} s", flush=True)
    for baseline in baselines.values():
        time_denoiser(baseline, layers, repeats=1, warmup=args.warmup)
    runs = {p: [] for p in denoisers}
    baseline_runs = {b: [] for b in baselines}
    for _ in range(args.repeats):
        for precision, denoiser in denoisers.items():
            runs[precision].append(denoiser(layers))
        for b, baseline in baselines.items():  # the evaluation's own timing (time_denoiser)
            baseline_runs[b].append(time_denoiser(baseline, layers, repeats=1, warmup=0)[1])
    totals = {}
    for precision, results in runs.items():
        network = statistics.median(r.network_seconds for r in results) * 1e3
        totals[precision] = statistics.median(r.seconds for r in results)
        denoiser = denoisers[precision]
        print(
            f"{name:6s} {precision:20s} {width}x{height} tile {denoiser.tile} ({results[0].tiles} per branch, halo "
            f"{denoiser.overlap}, receptive radius {receptive_radius(diffuse)}): network "
            f"{network:9.1f} ms/image, total {totals[precision] * 1e3:9.1f} ms/image  "
            f"[{', '.join(results[0].branches)}]",
            flush=True,
        )
    base = next(iter(totals))
    if len(totals) > 1:
        print(
            f"{name:6s} speed-up over {base}: "
            + ", ".join(f"{p} {totals[base] / s:.2f}x" for p, s in totals.items() if p != base),
            flush=True,
        )
    for b, seconds in baseline_runs.items():
        totals[b] = statistics.median(seconds)
        print(
            f"{b:6s} {width}x{height}: total {totals[b] * 1e3:9.1f} ms/image  [{baselines[b].device}]; "
            f"{name} / {b}: " + ", ".join(f"{p} {totals[p] / totals[b]:.2f}x" for p in denoisers),
            flush=True,
        )
    return totals


def make_baselines(names: list[str], device: str, width: int, height: int) -> dict[str, Denoiser]:
    """The evaluation's own baselines that run here (OIDN high quality on `device`; OptiX on CUDA)."""
    baselines = {}
    for name in names:
        reason = optix_unavailable_reason() if name == "optix" else None
        if reason:
            print(f"optix  {width}x{height}: not run: {reason}", flush=True)
        else:
            baselines[name] = OptixDenoiser() if name == "optix" else OidnDenoiser(quality="high", device=device)
    return baselines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="1280x720", help="WIDTHxHEIGHT")
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--engines", nargs="+", default=list(ENGINES), choices=list(ENGINES))
    parser.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=list(PRECISIONS))
    parser.add_argument(
        "--baselines",
        nargs="*",
        default=["oidn", "optix"],
        choices=["oidn", "optix"],
        help="also time these on the same image (OIDN high quality on --device; OptiX on CUDA)",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--tile", type=int, default=None, help="largest tile core edge (default: the denoiser's own); 0: no tiling"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1, help="untimed runs per precision first (>= 1)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--compile", action="store_true", help="torch.compile the generators")
    args = parser.parse_args()
    if args.warmup < 1:
        parser.error("--warmup must be >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.size.lower().split("x"))
    device = torch.device(args.device)
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    engine = resolve_engine(DEFAULTS.eval.engine, device)
    default = f"{engine} {precision_name(default_precision(engine, device))}"
    print(
        f"torch {torch.__version__} on {where}; denoiser default here: {default}"
        f"{'; compiled' if args.compile else ''}; median of {args.repeats} after {args.warmup} warm-up"
    )
    layers = synthetic_layers(height, width)
    baselines = make_baselines(args.baselines, args.device, width, height)
    ratios = {}
    for name in args.configs:
        totals = bench(name, layers, baselines, args)
        if name in RATIO_LINES and default in totals and "oidn" in totals:
            ratios[RATIO_LINES[name]] = totals[default] / totals["oidn"]
    for label, ratio in ratios.items():  # the default model and engine against OIDN high in this same run
        print(f"{label} time ratio: {ratio:.2f}  ({default}, {width}x{height})")


if __name__ == "__main__":
    main()
