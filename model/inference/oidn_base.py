"""OIDN's denoised radiance per branch: the base an admc+oidn refiner corrects (model.base "oidn" or "oidn-fast").

OIDN runs once per branch, not once on the combined image: diffuse with albedo and normal as guides,
specular alone (its reflections do not follow the first hit's albedo or normal). Measured on 20 scenes
of the pretraining corpus (experiments/compare_oidn_bases.py): the sum of the two branch outputs had a lower
relMSE and 1-SSIM than OIDN on the combined image at 4, 16 and 64 spp (1-SSIM at 4 spp 0.0431 against
0.0488), at about 1.9x the time, and each branch gets a base of its own signal.

Tiling (the stored bases, for tile.refiner_base) and inference (for the base its weights record) call the
same function on the same sanitised layers, so training and denoising see identical bases; the base names
each branch's OIDN quality (layout.BASE_QUALITIES).
"""

from __future__ import annotations

from importlib.metadata import version

import numpy as np

from admc.common import oidn
from admc.common.layout import BASE_QUALITIES


def describe(base: str) -> dict:
    """What produced the bases, stored with them: a refiner must see bases of the qualities it was trained
    on (whatever quality the evaluation's OIDN baseline runs at), and a later OIDN version gives others."""
    return {
        "method": "oidn",
        "base": base,
        "quality": BASE_QUALITIES[base],
        "per_branch": True,
        "pyoidn": version("pyoidn"),
    }


def oidn_bases(clean: dict[str, np.ndarray], base: str) -> dict[str, np.ndarray]:
    """{"diffuse": ..., ["specular": ...]} linear HDR (H, W, 3) float32 from sanitised layers
    (admc.common.buffers.sanitize: finite, radiance >= 0, albedo in [0, 1], normals in [-1, 1]), each
    branch's OIDN at the quality refining base `base` names."""
    quality = BASE_QUALITIES[base]
    bases = {"diffuse": oidn.denoise(clean["diffuse"], clean["albedo"], clean["normal"], quality=quality["diffuse"])}
    if "specular" in clean:
        bases["specular"] = oidn.denoise(clean["specular"], quality=quality["specular"])
    # OIDN's output is finite for finite input; negatives (ringing) are not radiance.
    return {
        branch: np.clip(np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)
        for branch, image in bases.items()
    }
