"""Validation of one branch on fixed val patches: PSNR, relMSE and 1-SSIM in linear radiance.

The metrics are the evaluation's own (admc.common.metrics, their torch twins): relMSE on linear
HDR values, PSNR and 1-SSIM on the 8-bit tone-mapped images. Each is computed per patch and averaged,
for the denoised output at every validation and, once per run, for its baseline: the noisy input (and OIDN's
output, for a refiner).
"""

from __future__ import annotations

import torch
from torch import Tensor

from admc.common.layout import ALBEDO
from admc.common.metrics import one_minus_ssim_torch, psnr_torch, relmse_torch

from ..nets.generator import Generator
from ..precision import MEMORY_FORMAT, autocast_for
from ..transforms import EPS


def linear_scale(features: Tensor, branch: str) -> Tensor | None:
    """What multiplies expm1 of a branch's values to give linear radiance: albedo + eps for diffuse, else None."""
    return features[:, ALBEDO] + EPS if branch == "diffuse" else None


def to_linear(x: Tensor, features: Tensor, branch: str) -> Tensor:
    """Inverse of the store's transforms: expm1(d) * (albedo + eps) for diffuse, expm1(s) for specular."""
    x, scale = torch.expm1(x.double()), linear_scale(features.double(), branch)
    return x if scale is None else x * scale


BLEND_SHARES = torch.linspace(0.0, 1.0, 21)
"""The shares of the network's output an OIDN blend may keep (train.oidn_blend): steps of 0.05."""


@torch.no_grad()
def validate(
    generator: Generator,
    val: dict[str, Tensor],
    branch: str,
    batch_size: int,
    device: torch.device,
    dtype: torch.dtype = torch.float32,
) -> tuple[dict[str, float], dict[str, Tensor], Tensor]:
    """({"psnr", "relmse", "one_minus_ssim"} of the generator's output averaged over the val patches, the
    same {"relmse", "one_minus_ssim"} per patch, the output in linear radiance), the generator run in `dtype`
    as in training (and as the denoiser runs it on the same machine)."""
    was_training = generator.training
    generator.eval()
    outputs = []
    for i in range(0, len(val["noisy"]), batch_size):
        noisy = val["noisy"][i : i + batch_size].to(device, memory_format=MEMORY_FORMAT)
        features = val["features"][i : i + batch_size].to(device, memory_format=MEMORY_FORMAT)
        base = val["base"][i : i + batch_size].to(device, memory_format=MEMORY_FORMAT) if "base" in val else None
        with autocast_for(device, dtype):
            outputs.append(generator(noisy, features, base).float().cpu())
    generator.train(was_training)
    ref = to_linear(val["reference"], val["features"], branch)
    linear = to_linear(torch.cat(outputs), val["features"], branch)
    per_patch = _per_patch(linear, ref)
    return (
        {k: float(v.mean()) for k, v in per_patch.items()},
        {k: per_patch[k] for k in ("relmse", "one_minus_ssim")},
        linear,
    )


def best_blend(
    output: Tensor, val: dict[str, Tensor], branch: str, partner: Tensor | None = None
) -> tuple[float, float]:
    """(share, mean relMSE) of the blend share * output + (1 - share) * OIDN's output with the lowest mean
    relMSE on the val patches, the share from BLEND_SHARES (1: the output alone). Two denoisers whose errors
    are only partly correlated average to less error than either: what train.oidn_blend ships. `partner`:
    the linear output of OIDN's networks fine-tuned on the domain (oidn_partner.py), in place of the store's."""
    ref = to_linear(val["reference"], val["features"], branch)
    oidn = partner if partner is not None else to_linear(val["oidn"], val["features"], branch)
    means = torch.stack([relmse_torch(w * output + (1 - w) * oidn, ref).mean() for w in BLEND_SHARES.double()])
    best = int(torch.argmin(means))
    return round(float(BLEND_SHARES[best]), 2), float(means[best])


def baseline_scores(val: dict[str, Tensor], branch: str) -> dict[str, float]:
    """The same averages for what the generator starts from, which a run must beat: "noisy_psnr",
    "noisy_relmse", ..., for a refiner "base_*" of its OIDN base, and "oidn_*" of OIDN's output for the
    branch where the store holds it (what the user compares with). Fixed for a run: computed once."""
    ref = to_linear(val["reference"], val["features"], branch)
    return {
        f"{name}_{k}": float(v.mean())
        for name in ("noisy", "base", "oidn")
        if name in val
        for k, v in _per_patch(to_linear(val[name], val["features"], branch), ref).items()
    }


def _per_patch(x: Tensor, ref: Tensor) -> dict[str, Tensor]:
    """Each patch's {"psnr", "relmse", "one_minus_ssim"} of linear `x` against `ref`."""
    return {"psnr": psnr_torch(x, ref), "relmse": relmse_torch(x, ref), "one_minus_ssim": one_minus_ssim_torch(x, ref)}
