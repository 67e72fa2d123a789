"""Validation of one branch on fixed val patches: PSNR and relMSE in linear radiance.

The metrics follow the evaluation's definitions (pipeline/evaluation/metrics.py, not imported: model never
imports pipeline): relMSE = mean((x - y)^2 / (y^2 + 0.01)) on linear HDR values; PSNR on 8-bit
images round(255 * clip(x^(1/2.2), 0, 1)), capped at 100 dB. Both are computed per patch and
averaged, for the denoised output and, as the baseline, the noisy input.
"""
from __future__ import annotations

import torch
from torch import Tensor

from .precision import autocast_for, memory_format_for
from .generator import Generator
from .transforms import EPS

RELMSE_EPS = 1e-2
GAMMA = 2.2
PSNR_CAP_DB = 100.0
ALBEDO = slice(4, 7)  # feature channels normal(3), depth(1), albedo(3)


def to_linear(x: Tensor, features: Tensor, branch: str) -> Tensor:
    """Inverse of the store's transforms: expm1(d) * (albedo + eps) for diffuse, expm1(s) for specular."""
    x = torch.expm1(x.double())
    return x * (features[:, ALBEDO].double() + EPS) if branch == "diffuse" else x


def relmse(x: Tensor, ref: Tensor) -> Tensor:
    """Per-sample relMSE of (N, C, H, W) linear images."""
    return ((x - ref) ** 2 / (ref ** 2 + RELMSE_EPS)).flatten(1).mean(1)


def psnr(x: Tensor, ref: Tensor) -> Tensor:
    """Per-sample PSNR in dB on the 8-bit gamma-2.2 images, capped at 100 dB."""
    def ldr(v: Tensor) -> Tensor:
        return torch.round(255 * torch.clamp(v.clamp(min=0) ** (1 / GAMMA), 0, 1))
    mse = ((ldr(x) - ldr(ref)) ** 2).flatten(1).mean(1)
    db = 10 * torch.log10(255.0 ** 2 / mse.clamp(min=1e-30))
    return torch.where(mse == 0, torch.full_like(db, PSNR_CAP_DB), db.clamp(max=PSNR_CAP_DB))


@torch.no_grad()
def validate(generator: Generator, val: dict[str, Tensor], branch: str, batch_size: int,
             device: torch.device, dtype: torch.dtype = torch.float32) -> dict[str, float]:
    """{"psnr", "relmse", "noisy_psnr", "noisy_relmse"} averaged over the val patches, the generator
    run in `dtype` as in training (and as the denoiser runs it on the same machine)."""
    was_training = generator.training
    generator.eval()
    outputs = []
    memory = memory_format_for(device, dtype)
    for i in range(0, len(val["noisy"]), batch_size):
        noisy = val["noisy"][i:i + batch_size].to(device, memory_format=memory)
        features = val["features"][i:i + batch_size].to(device, memory_format=memory)
        with autocast_for(device, dtype):
            outputs.append(generator(noisy, features).float().cpu())
    generator.train(was_training)
    features = val["features"]
    ref = to_linear(val["reference"], features, branch)
    out = to_linear(torch.cat(outputs), features, branch)
    noisy = to_linear(val["noisy"], features, branch)
    return {"psnr": float(psnr(out, ref).mean()), "relmse": float(relmse(out, ref).mean()),
            "noisy_psnr": float(psnr(noisy, ref).mean()), "noisy_relmse": float(relmse(noisy, ref).mean())}
