#!/usr/bin/env python3
"""Is OIDN better run per branch (diffuse with guides + specular alone) or once on the combined image?

    python experiments/compare_oidn_bases.py RENDERS_DIR [--every 6]

RENDERS_DIR is a workdir's `renders/` folder (one folder per scene: spp*.exr and reference.exr). Use a
training corpus, never a test set: the answer decides what admc+oidn refines (model/inference/oidn_base.py).
Prints relMSE and 1-SSIM averages per spp against the references, and OIDN's total time for each way.

Backs: docs/design-decisions.md, "OIDN per branch" (on 20 pretraining scenes the per-branch sum had the
lower relMSE and 1-SSIM at every spp, at about 1.9x OIDN's time).
"""

import argparse
import time
from pathlib import Path

import numpy as np

from admc.common import oidn
from admc.common.buffers import sanitize
from admc.common.layout import BASE_QUALITIES
from admc.common.metrics import one_minus_ssim, relmse
from admc.model.inference.oidn_base import oidn_bases
from admc.stores.exr import read_exr

BASE = "oidn"  # the refiner's bases this comparison was made for: OIDN high on both branches


def combined(layers: dict) -> np.ndarray:
    color = layers["diffuse"] + layers.get("specular", 0.0)
    return oidn.denoise(color, layers["albedo"], layers["normal"], quality=BASE_QUALITIES[BASE]["diffuse"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("renders", type=Path)
    parser.add_argument("--every", type=int, default=6, help="use every n-th scene folder")
    args = parser.parse_args()
    scenes = sorted(p for p in args.renders.iterdir() if (p / "reference.exr").is_file())[:: args.every]
    scores, seconds = {}, {"combined": 0.0, "per branch": 0.0}
    for scene in scenes:
        ref = read_exr(scene / "reference.exr")
        ref = ref["diffuse"] + ref.get("specular", 0.0)
        for noisy in sorted(scene.glob("spp*.exr")):
            layers = {
                name: sanitize(a, name)[0]
                for name, a in read_exr(noisy).items()
                if name in ("diffuse", "specular", "albedo", "normal")
            }
            spp = int(noisy.stem[3:])
            start = time.perf_counter()
            images = {"combined": combined(layers)}
            seconds["combined"] += time.perf_counter() - start
            start = time.perf_counter()
            bases = oidn_bases(layers, BASE)
            images["per branch"] = bases["diffuse"] + bases.get("specular", 0.0)
            seconds["per branch"] += time.perf_counter() - start
            for way, image in images.items():
                scores.setdefault((spp, way), []).append((relmse(image, ref), one_minus_ssim(image, ref)))
    print(f"{len(scenes)} scenes of {args.renders}")
    for (spp, way), values in sorted(scores.items()):
        rel, ssim = np.mean(values, axis=0)
        print(f"{spp:4d} spp  {way:10s}  relMSE {rel:.5f}  1-SSIM {ssim:.5f}")
    print("OIDN seconds: " + ", ".join(f"{way} {s:.2f}" for way, s in seconds.items()))


if __name__ == "__main__":
    main()
