#!/usr/bin/env python3
"""Do admc and OIDN make the same errors? Scores each, and their per-pixel mean, against the references.

    python experiments/blend_check.py SCENE_DIR ... [--weights FILE] [--ensemble N] [--no-dark-pass] [--threads 2]

Each SCENE_DIR is one scene folder of a workdir's `renders/` (spp*.exr, reference.exr and their .json sidecars).
admc runs as Table 1 runs it (the default config's eval.ensemble and eval.dark_pass), OIDN as Table 1's
baseline (eval.oidn_quality).
Prints, per family and spp, the relMSE and 1-SSIM averages of OIDN, admc, their mean, and their mean with
the environment pixels (coverage 0) taken from admc alone, each as a multiple of OIDN's, and on how many
images each of the two means beats both admc and OIDN. Where the mean beats both, the two make partly
independent errors: what a refiner of OIDN that also sees admc's output could use. Point it at scenes
you do not test on.

Backs: docs/results/2026-12-02-generalization-and-refiner.md (the mean beats both on rooms and
tabletops, 36 scenes outside every test set; not on the studios).
"""

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from admc.common.metrics import one_minus_ssim, relmse
from admc.model.inference.denoiser import load_denoiser
from admc.model.inference.options import DenoiserOptions
from admc.pipeline.config import load_config
from admc.pipeline.evaluation.baselines import OidnDenoiser
from admc.pipeline.evaluation.inputs import by_scene, find_test_images, read_reference
from admc.pipeline.evaluation.records import EvalError
from admc.pipeline.weights import WEIGHTS_DIR
from admc.stores.exr import read_exr

SHIPPED = WEIGHTS_DIR / "admc-small-pretrained.pt"
METHODS = ("oidn", "admc", "mean", "mean, environment from admc")


def outputs(admc, oidn, layers: dict) -> dict[str, np.ndarray]:
    ours, theirs = admc(layers).image, oidn.denoise(layers)
    mean = 0.5 * (ours + theirs)
    environment = layers["coverage"][..., :1] <= 0 if "coverage" in layers else np.zeros_like(mean[..., :1], bool)
    return dict(zip(METHODS, (theirs, ours, mean, np.where(environment, ours, mean))))


def main() -> None:
    table1 = load_config().eval
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", type=Path, nargs="+", help="scene folders of a renders/ directory")
    parser.add_argument("--weights", type=Path, default=SHIPPED)
    parser.add_argument("--ensemble", type=int, default=table1.ensemble)
    parser.add_argument("--no-dark-pass", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    try:  # Table 1's own reading of a renders folder: its checks name a missing or broken file
        images = [image for scene in args.scenes for image in find_test_images(scene.parent, [scene.name])]
    except EvalError as exc:
        parser.error(str(exc))
    torch.set_num_threads(args.threads)
    admc = load_denoiser(
        args.weights, DenoiserOptions(ensemble=args.ensemble, dark_pass=table1.dark_pass and not args.no_dark_pass)
    )
    oidn = OidnDenoiser(quality=table1.oidn_quality)
    scores = defaultdict(list)  # (family, spp) -> per image: [relMSE per method, 1-SSIM per method]
    for scene_id, group in by_scene(images).items():
        reference_path = group[0].reference_path
        family = json.loads(reference_path.with_suffix(".json").read_text())["family"]
        ref, _ = read_reference(reference_path)
        for test in group:
            denoised = outputs(admc, oidn, read_exr(test.noisy_path)).values()
            row = [relmse(x, ref) for x in denoised] + [one_minus_ssim(x, ref) for x in denoised]
            scores[family, test.spp].append(row)
        print(f"scored {scene_id}", flush=True)
    n = len(METHODS)
    print(
        f"\nper family and spp, each average as a multiple of OIDN's ({', '.join(METHODS)}); "
        "'beats both': images where the method beats admc and OIDN alone"
    )
    for (family, spp), rows in sorted(scores.items(), key=lambda item: (item[0][1], item[0][0])):
        table = np.array(rows)
        for metric, part in (("relMSE", table[:, :n]), ("1-SSIM", table[:, n:])):
            ratios = " ".join(f"{r:.3f}" for r in part.mean(axis=0) / part[:, 0].mean())
            beats = " ".join(str(int((part[:, i] < part[:, :2].min(axis=1)).sum())) for i in (2, 3))
            print(f"{spp:4d} spp  {family:10s} n={len(table):2d}  {metric:6s}  {ratios}   beats both: {beats}")


if __name__ == "__main__":
    main()
