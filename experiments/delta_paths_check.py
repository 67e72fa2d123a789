#!/usr/bin/env python3
"""Pixels that see the environment only through mirrors or smooth glass: denoised now, passed through before.

    python experiments/delta_paths_check.py [--size 128] [--spp 4 16 64] [--reference-spp 1024] [--threads 2]

Renders a scene written here (three mirror spheres and a glass sphere, nothing else, under a procedural
environment map with a sun, stripes and a checkered ground) with the admc_split integrator, and scores
against a high-spp render of it: the noisy input, OIDN, and the shipped admc and admc+oidn weights (run
as Table 1 runs them: the default config's eval.ensemble and eval.dark_pass), each as they run now and as
they ran before, when those pixels had coverage 0 and were passed through (both kept the noisy input).
Prints relMSE and 1-SSIM over the whole image and
relMSE over the pixels the change touches.
"""

import argparse

import numpy as np
import torch

from admc.common.metrics import one_minus_ssim, relmse
from admc.model.inference.denoiser import load_denoiser
from admc.model.inference.options import DenoiserOptions
from admc.pipeline.config import load_config
from admc.pipeline.evaluation.baselines import OidnDenoiser
from admc.pipeline.render.integrator import render_buffers
from admc.pipeline.render.variants import use_variant
from admc.pipeline.weights import WEIGHTS_DIR


def environment_map(width: int = 512, height: int = 256) -> np.ndarray:
    """A lat-long HDR sky: blue gradient, a sun, a band of thin stripes at the horizon, a checkered ground."""
    theta = (np.arange(height) + 0.5) / height * np.pi  # 0 at the zenith
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    up = np.cos(theta)
    sky = np.stack([0.3 + 0.2 * up, 0.5 + 0.3 * up, 1.0 + 0.2 * up], axis=-1)
    stripes = (np.abs(up) < 0.15) & (np.sin(phi * 48) > 0)
    sky[stripes] = [2.0, 1.6, 0.6]
    ground = up < -0.15
    checker = (np.floor(phi * 8 / np.pi) + np.floor(theta * 8 / np.pi)) % 2
    sky[ground] = np.where(checker[ground, None] > 0, [0.6, 0.5, 0.4], [0.05, 0.05, 0.08])
    sun = np.arccos(np.clip(np.sin(theta) * np.sin(phi) * np.sin(0.8) + up * np.cos(0.8), -1, 1)) < 0.04
    sky[sun] = [400.0, 380.0, 330.0]
    return sky.astype(np.float32)


def mirror_spheres(mi, size: int):
    """Three mirror spheres (silver, gold-tinted, a small one in front) and a glass sphere, nothing else."""
    T = mi.ScalarTransform4f
    return mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "perspective",
                "fov": 45,
                "to_world": T().look_at(origin=[0, 1.2, 5], target=[0, 0.2, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}},
            },
            "sky": {"type": "envmap", "bitmap": mi.Bitmap(environment_map())},
            "silver": {
                "type": "sphere",
                "center": [-1.1, 0.3, 0],
                "radius": 0.8,
                "bsdf": {"type": "conductor", "material": "Ag"},
            },
            "gold": {
                "type": "sphere",
                "center": [1.1, 0.3, -0.3],
                "radius": 0.8,
                "bsdf": {"type": "conductor", "material": "Au"},
            },
            "small": {
                "type": "sphere",
                "center": [0.2, -0.3, 1.3],
                "radius": 0.35,
                "bsdf": {"type": "conductor", "material": "Cr"},
            },
            "glass": {"type": "sphere", "center": [0.1, 0.9, -1.5], "radius": 0.6, "bsdf": {"type": "dielectric"}},
        }
    )


def old_layers(layers: dict) -> tuple[dict, np.ndarray]:
    """The layers as the integrator wrote them before: coverage 0 where no sample reached a non-delta vertex
    (here: every sphere pixel; the rest is unchanged). Returns them and the mask of the pixels that differ."""
    touched = layers["coverage"][..., 0] > 0  # the scene has no non-delta surface at all
    return {**layers, "coverage": np.zeros_like(layers["coverage"])}, touched


def main() -> None:
    table1 = load_config().eval
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    mi = __import__("mitsuba")
    use_variant("auto")
    scene = mirror_spheres(mi, args.size)
    reference = render_buffers(scene, args.reference_spp, seed=1000)
    ref = reference["diffuse"] + reference["specular"]
    oidn = OidnDenoiser(quality=table1.oidn_quality)
    learned = {
        name: load_denoiser(
            WEIGHTS_DIR / f"admc-small-{file}.pt", DenoiserOptions(ensemble=table1.ensemble, dark_pass=table1.dark_pass)
        )
        for name, file in (("admc", "pretrained"), ("admc+oidn", "refiner"))
    }
    print(f"{args.size}x{args.size}, reference {args.reference_spp} spp; relMSE (whole image, touched pixels), 1-SSIM")
    for spp in args.spp:
        layers = render_buffers(scene, spp, seed=spp)
        old, touched = old_layers(layers)
        noisy = layers["diffuse"] + layers["specular"]
        images = {"noisy": noisy, "oidn": oidn.denoise(layers)}
        for name, denoiser in learned.items():
            images[f"{name} before"] = denoiser(old).image
            images[f"{name} now"] = denoiser(layers).image
        print(f"{spp} spp, {int(touched.sum())} touched pixels of {touched.size}")
        for name, image in images.items():
            print(
                f"  {name:16s} relMSE {relmse(image, ref):.5f}  "
                f"touched {relmse(image[touched][None], ref[touched][None]):.5f}"
                f"  1-SSIM {one_minus_ssim(image, ref):.5f}"
            )


if __name__ == "__main__":
    main()
