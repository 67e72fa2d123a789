#!/usr/bin/env python3
"""How much does exposure normalisation (model/inference/exposure.py) change a denoiser on dim and native images?

    python experiments/exposure_check.py STORE RENDERS_DIR WEIGHTS [--split val] [--scales 1 0.25 0.0625]

Scales the noisy renders and references of STORE's `--split` scenes (never a test set: the answer
decides what inference does) by each factor, an exact exposure change, and prints per spp and scale
the denoiser's relMSE as a multiple of its input's, without and with the normalisation, and how
often the normalisation is worse. Also prints the brightness percentiles that set TRAINED_BRIGHTNESS
when pointed at a pretraining store with `--split train --scales 1`.

Backs: docs/design-decisions.md, "Exposure normalisation" (at 1/16 exposure, 2.08x the input's relMSE
at 64 spp without it, 0.36x with it; TRAINED_BRIGHTNESS = 0.21, the pretraining corpus's median).
"""

import argparse
from pathlib import Path

import numpy as np
import torch

from admc.common.metrics import relmse
from admc.model.inference.denoiser import load_denoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.exposure import brightness
from admc.pipeline.evaluation.baselines import noisy_color
from admc.pipeline.evaluation.inputs import read_reference
from admc.stores.exr import read_exr
from admc.stores.patches.format import list_scenes


def scaled(layers: dict, factor: float) -> dict:
    return {
        name: value * np.float32(factor) if name in ("diffuse", "specular") else value for name, value in layers.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("store", type=Path)
    parser.add_argument("renders", type=Path)
    parser.add_argument("weights", type=Path)
    parser.add_argument("--split", default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.25, 0.0625])
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    plain = load_denoiser(args.weights, DenoiserOptions(normalize_exposure=False))
    normed = load_denoiser(args.weights)
    results: dict[tuple[int, float], list[tuple[float, float]]] = {}
    levels: dict[int, list[float]] = {}
    for scene in list_scenes(args.store, args.split):
        reference, _ = read_reference(args.renders / scene / "reference.exr")
        for spp in args.spp:
            layers = read_exr(args.renders / scene / f"spp{spp:04d}.exr")
            levels.setdefault(spp, []).append(brightness(noisy_color(layers)))
            for factor in args.scales:
                noisy, ref = scaled(layers, factor), reference * np.float32(factor)
                input_error = relmse(noisy_color(noisy), ref)
                results.setdefault((spp, factor), []).append(
                    (relmse(plain.denoise(noisy), ref) / input_error, relmse(normed.denoise(noisy), ref) / input_error)
                )
    print(f"{args.split} scenes of {args.store}: denoiser relMSE / input relMSE, mean over scenes")
    print("spp  scale     plain  normalised  normalised worse on")
    for (spp, factor), pairs in sorted(results.items(), key=lambda kv: (kv[0][0], -kv[0][1])):
        a = np.array(pairs)
        worse = int((a[:, 1] > a[:, 0] * 1.001).sum())
        print(f"{spp:3d}  {factor:<8g}  {a[:, 0].mean():.4f}  {a[:, 1].mean():.4f}      {worse} of {len(a)}")
    for spp, values in sorted(levels.items()):
        print(
            f"brightness at {spp} spp, percentiles 10/50/90: "
            + " / ".join(f"{v:.4f}" for v in np.percentile(values, [10, 50, 90]))
        )


if __name__ == "__main__":
    main()
