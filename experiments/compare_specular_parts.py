#!/usr/bin/env python3
"""What does each part of admc+oidn's specular half add: its OIDN base's quality, and its refiner network?

    python experiments/compare_specular_parts.py RENDERS_DIR [--weights weights]

RENDERS_DIR is a workdir's `renders/` folder (one folder per scene: spp*.exr and reference.exr), of scenes
you do not test on (the out-of-family set, unseen corpus scenes). The shipped weights run as `admc-pipe
eval` runs them (the default engine, keep_resolved); their branches are recombined into five variants of
admc+oidn, each scored against the references. Prints relMSE and 1-SSIM averages per spp as multiples of
OIDN `high`'s (a ratio of the averages, as Table 1's columns compare).

Backs: docs/results/2026-12-04-specular-base-and-refiner.md (every variant that takes admc+oidn to 2.5x
OIDN's time costs 1-3% of its scores; admc's own specular network is no substitute for an OIDN base).
"""

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from admc.common import oidn
from admc.common.metrics import one_minus_ssim, relmse
from admc.model.inference.denoiser import load_denoiser, sanitize_layers
from admc.model.inference.options import DenoiserOptions
from admc.pipeline.evaluation.baselines import OidnDenoiser
from admc.pipeline.evaluation.inputs import find_test_images, read_reference
from admc.stores.exr import read_exr


def _specular(part: np.ndarray | None) -> np.ndarray | float:
    return 0.0 if part is None else part  # a scene without specular materials has no specular layer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("renders", type=Path)
    parser.add_argument("--weights", type=Path, default=Path("weights"), help="the folder of the shipped weights")
    args = parser.parse_args()
    settings = {"engine": "auto", "keep_resolved": True}
    admc = load_denoiser(args.weights / "admc-small-pretrained.pt", DenoiserOptions(**settings))
    refiner = load_denoiser(args.weights / "admc-small-refiner.pt", DenoiserOptions(**settings))
    refiner_fast = load_denoiser(args.weights / "admc-small-refiner-fast.pt", DenoiserOptions(**settings))
    baseline = OidnDenoiser("high")
    scores = defaultdict(lambda: defaultdict(list))
    for test in find_test_images(args.renders):
        reference, _ = read_reference(test.reference_path)
        layers = read_exr(test.noisy_path)
        own, refined = admc(layers), refiner(layers)
        clean, _ = sanitize_layers(layers)
        oidn_specular = {
            quality: oidn.denoise(clean["specular"], quality=quality) if "specular" in clean else 0.0
            for quality in ("high", "fast")
        }
        variants = {
            "oidn high": baseline.denoise(layers),
            "refiner on high / refiner on high (default)": refined.image,
            "refiner on high / refiner on fast (oidn-fast)": refiner_fast(layers).image,
            "refiner on high / OIDN high as is": refined.diffuse + oidn_specular["high"],
            "refiner on high / OIDN fast as is": refined.diffuse + oidn_specular["fast"],
            "refiner on high / admc's specular": refined.diffuse + _specular(own.specular),
            "admc alone": own.image,
        }
        for name, image in variants.items():
            scores[test.spp][name].append((relmse(image, reference), one_minus_ssim(image, reference)))
        print(f"{test.scene_id} @ {test.spp} spp", flush=True)
    for spp in sorted(scores):
        oidn_mean = np.mean(scores[spp]["oidn high"], axis=0)
        for name, values in scores[spp].items():
            mean = np.mean(values, axis=0) / oidn_mean
            print(f"{spp:4d} spp  {name:48s} relMSE {mean[0]:.3f}x  1-SSIM {mean[1]:.3f}x")


if __name__ == "__main__":
    main()
