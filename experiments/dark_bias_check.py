#!/usr/bin/env python3
"""What the diffuse network adds to its input, by irradiance level: where does an image get darker?

    python experiments/dark_bias_check.py WEIGHTS RENDERS_DIR [--scenes studio-200000007 ...] [--spp 64]

For each scene folder of RENDERS_DIR (a run's `renders/`: spp*.exr and reference.exr), denoises the
`--spp` render and bins the fully covered, lit pixels by the reference's irradiance in the network's own
log1p domain (diffuse / (albedo + eps), at the exposure the denoiser chose). Per bin it prints the mean
correction (output - input), the output's and the input's mean signed and absolute error against the
reference, and the output's bias relative to the bin's mean. The networks predict an additive
correction in that domain, so an error of the same absolute size at every level is a small fraction
of a bright pixel and a large one of a deep shadow; and above log1p 3, where the training corpora have
almost no pixels, the correction can exceed the input's own error.
Point it at scenes you do not test on.

Backs: docs/results/2026-12-01-worse-than-input-cells.md (a log-domain offset of 5e-4 to 1e-3 at every
level, a 32% darkening below an irradiance of 3e-3), which led to the dark pass.
"""

import argparse
from pathlib import Path

import numpy as np
import torch

from admc.model.inference.denoiser import load_denoiser
from admc.model.transforms import EPS
from admc.stores.exr import read_exr

EDGES = (0.0, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 2.0, 3.0, 4.0, 10.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("weights", type=Path)
    parser.add_argument("renders", type=Path)
    parser.add_argument("--scenes", nargs="+", help="scene folders to read (default: all)")
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    denoiser = load_denoiser(args.weights)
    for scene in args.scenes or sorted(p.name for p in args.renders.iterdir() if p.is_dir()):
        noisy = read_exr(args.renders / scene / f"spp{args.spp:04d}.exr")
        reference = read_exr(args.renders / scene / "reference.exr")
        result = denoiser(noisy)
        gain, scale = result.exposure_gain, noisy["albedo"] + EPS

        def network_domain(diffuse):
            return np.log1p(gain * diffuse / scale)

        start, out, truth = (network_domain(x) for x in (noisy["diffuse"], result.diffuse, reference["diffuse"]))
        level = truth.mean(-1)
        lit = (reference["diffuse"].mean(-1) > 1e-6) & (noisy["coverage"][..., 0] > 0.999)
        print(
            f"{scene} @ {args.spp} spp (exposure gain {gain:g}): log1p irradiance bin, pixels, mean correction, "
            f"output - reference mean and |.| (input's in brackets), output's relative bias"
        )
        for low, high in zip(EDGES, EDGES[1:]):
            m = lit & (level >= low) & (level < high)
            if m.sum() < 20:
                continue
            err, err_in = (out - truth)[m], (start - truth)[m]
            print(
                f"  [{low:g}, {high:g}) {m.sum():6d}  {(out - start)[m].mean():+.5f}  {err.mean():+.5f} "
                f"({err_in.mean():+.5f})  {np.abs(err).mean():.5f} ({np.abs(err_in).mean():.5f})  "
                f"{err.mean() / truth[m].mean():+.3f}"
            )


if __name__ == "__main__":
    main()
