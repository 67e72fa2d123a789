"""Generator and WGAN-GP critic losses, weighted as in the authors' code.

Generator: l1_weight * L1 + adv_weight * (-mean D(fake)), 1 : 5e-3 (the paper's 200:1), plus, when
ssim_weight > 0, ssim_weight * (1 - SSIM) of the display images that Table 1's 1-SSIM compares.
Critic: (mean D(fake) - mean D(real)) / 2 + gp_weight * GP. The 1/2 on the Wasserstein term is the
authors' (it averages their "real" and "fake" loss terms); the penalty is not halved.
OIDN's networks, fine-tuned as admc's blend partner, have their own: L1, or OIDN's L1 + MS-SSIM mix (oidn_loss).
All losses are computed in float32, whatever precision the networks ran in.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from admc.common.metrics import GAMMA, LDR_RANGE, SSIM_K1, SSIM_K2, SSIM_RADIUS, ssim_map_torch, ssim_moments_torch

DISPLAY_OFFSET = 1e-5  # linear; keeps the gamma curve's slope finite at 0 (below 8-bit level 1, 5.1e-6)


def log_floor(y: Tensor, floor: float) -> Tensor:
    """log(expm1(y) + floor) for y >= 0, continued below 0 by its tangent at 0, log(floor) + y / floor.

    The networks' values y are log1p of linear radiance v, so this is log(v + floor): floor = 1 gives y
    itself, and a smaller floor weighs a dark pixel's error up to 1 / floor times more. Written as
    y + log1p((floor - 1) e^-y), it stays finite for any y, and so does its gradient (at most 1 / floor).
    """
    if floor == 1.0:
        return y
    upper = y.clamp(min=0)
    upper = upper + torch.log1p((floor - 1.0) * torch.exp(-upper))
    return torch.where(y >= 0, upper, math.log(floor) + y / floor)


def display(linear: Tensor) -> Tensor:
    """The 8-bit display values (0..255, unrounded) of linear radiance, as metrics.to_ldr encodes it:
    clipped to [0, 1] and gamma-encoded, the curve shifted by DISPLAY_OFFSET so that its slope stays finite."""
    v = linear.clamp(0.0, 1.0)
    return LDR_RANGE * ((v + DISPLAY_OFFSET) ** (1.0 / GAMMA) - DISPLAY_OFFSET ** (1.0 / GAMMA))


def display_ssim_loss(fake: Tensor, real: Tensor, linear_scale: Tensor | None = None) -> Tensor:
    """1 - mean SSIM (metrics.ssim's window and constants) of the display images of log1p values `fake`
    and `real`, made linear as expm1(.) * linear_scale (the diffuse branch's albedo + eps; None: 1).

    Why: relMSE and the log-domain L1 barely see an error of a few 8-bit levels in a deep shadow, which
    the gamma curve and SSIM's normalisation by local contrast make one of the largest in 1-SSIM.
    Always float32, autocast off: its variances are blur(x^2) - blur(x)^2 of values up to 255, which in
    bf16 (8 significant bits) lose everything below ~250 to cancellation, far above SSIM's c2 = 58.5, and
    bf16 training with the term then drifted away from its start (docs/results/2026-12-02-bf16-ssim-loss.md).
    """
    with torch.autocast(device_type=fake.device.type, enabled=False):
        fake_linear, real_linear = torch.expm1(fake.float()), torch.expm1(real.float())
        if linear_scale is not None:
            fake_linear, real_linear = fake_linear * linear_scale.float(), real_linear * linear_scale.float()
        return 1.0 - ssim_map_torch(display(fake_linear), display(real_linear)).mean()


def ms_ssim(a: Tensor, b: Tensor, data_range: float = 1.0, max_scales: int = 5) -> Tensor:
    """Mean multi-scale SSIM (Wang et al. 2003) of (N, C, H, W) images, with equal weights over the scales, as
    OIDN's training computes it (RenderKit/oidn training/ssim.py): the contrast-structure term at each scale
    but the coarsest, full SSIM there, halving by 2x2 averages between. As many scales as keep the 11x11
    window inside the image, up to `max_scales` (4 for 128x128 patches, where OIDN's 256x256 tiles get 5)."""
    scales = 1
    while scales < max_scales and min(a.shape[-2:]) >> scales >= 2 * SSIM_RADIUS + 1:
        scales += 1
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    product = torch.ones(a.shape[:2], device=a.device, dtype=a.dtype)
    for scale in range(scales):
        mu_a, mu_b, var_a, var_b, cov = ssim_moments_torch(a, b)
        term = (2 * cov + c2) / (var_a + var_b + c2)
        if scale == scales - 1:
            term = term * (2 * mu_a * mu_b + c1) / (mu_a**2 + mu_b**2 + c1)
        # clamped, not relu'd as OIDN's: a power below 1 of 0 has an infinite slope
        product = product * term.mean(dim=(2, 3)).clamp(min=1e-6) ** (1.0 / scales)
        a, b = F.avg_pool2d(a, 2), F.avg_pool2d(b, 2)
    return product.mean()


OIDN_MSSSIM_SHARE = 0.84
"""OIDN's own training loss (RenderKit/oidn training, loss.py's default `l1_msssim`, after Zhao et al. 2017):
0.16 L1 + 0.84 (1 - MS-SSIM) of the PU-transferred values."""


def oidn_loss(output: Tensor, target: Tensor, kind: str) -> Tensor:
    """The loss OIDN's networks fine-tune with (train.oidn_loss), on values in OIDN's PU domain (about 0..1):
    "l1", or "l1_msssim", the mix OIDN was trained with. Always float32."""
    output, target = output.float(), target.float()
    l1 = (output - target).abs().mean()
    if kind == "l1":
        return l1
    with torch.autocast(device_type=output.device.type, enabled=False):
        return (1 - OIDN_MSSSIM_SHARE) * l1 + OIDN_MSSSIM_SHARE * (1 - ms_ssim(output, target))


def generator_loss(
    fake: Tensor,
    real: Tensor,
    critic_fake: Tensor | None,
    l1_weight: float = 1.0,
    adv_weight: float = 5e-3,
    adversarial: bool = True,
    l1_floor: float = 1.0,
    ssim_weight: float = 0.0,
    linear_scale: Tensor | None = None,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Total generator loss and its detached parts ("l1", "ssim" when weighted, "adversarial" when on).

    `critic_fake` is D(fake) with the graph to the generator kept; `adversarial=False` is the
    paper's "L1 only" ablation, and then `critic_fake` may be None. The L1 term compares
    log_floor(., l1_floor) of both (1.0: the networks' own log1p domain); the SSIM term is
    display_ssim_loss with `linear_scale`.
    """
    if fake.shape != real.shape:
        raise ValueError(f"generator_loss: fake {tuple(fake.shape)} and real {tuple(real.shape)} differ in shape")
    l1 = F.l1_loss(log_floor(fake.float(), l1_floor), log_floor(real.float(), l1_floor))
    parts = {"l1": l1.detach()}
    total = l1_weight * l1
    if ssim_weight > 0:
        ssim = display_ssim_loss(fake, real, linear_scale)
        parts["ssim"] = ssim.detach()
        total = total + ssim_weight * ssim
    if not adversarial:
        return total, parts
    if critic_fake is None:
        raise ValueError("generator_loss: critic_fake is required when adversarial=True")
    adv = -critic_fake.float().mean()
    parts["adversarial"] = adv.detach()
    return total + adv_weight * adv, parts


def gradient_penalty(critic: nn.Module, real: Tensor, fake: Tensor, shard: tuple[int, int] = (0, 1)) -> Tensor:
    """WGAN-GP penalty mean((||grad_x D(x)||_2 - 1)^2) at per-sample uniform interpolates of real and fake.

    With `shard` = (rank, world) of a data-parallel step, the batch is this rank's slice of the global
    batch: every rank draws the whole global batch's mixing weights and takes its slice, so the ranks
    together use (and consume the RNG for) exactly the weights a single process would.

    Runs with autocast off and float32 inputs: the gradient norm of a bf16/fp16 critic is too
    coarse (and overflows in fp16), and it is what enforces the Lipschitz constraint. The graph
    is kept (create_graph) so the penalty trains the critic. `fake` is detached here.
    """
    if real.shape != fake.shape:
        raise ValueError(f"gradient_penalty: real {tuple(real.shape)} and fake {tuple(fake.shape)} differ in shape")
    with torch.autocast(device_type=real.device.type, enabled=False):
        real32, fake32 = real.detach().float(), fake.detach().float()
        rank, world = shard
        n = real.shape[0]
        alpha = torch.rand((n * world,) + (1,) * (real.ndim - 1), device=real.device, dtype=torch.float32)
        alpha = alpha[rank * n : (rank + 1) * n]
        interpolates = (alpha * real32 + (1 - alpha) * fake32).requires_grad_(True)
        scores = critic(interpolates).float()
        (grad,) = torch.autograd.grad(scores.sum(), interpolates, create_graph=True)
        # The tiny epsilon keeps the norm's gradient finite where grad is exactly 0.
        norm = torch.sqrt(grad.flatten(1).pow(2).sum(dim=1) + 1e-12)
        return (norm - 1).pow(2).mean()


def critic_loss(
    critic: nn.Module, real: Tensor, fake: Tensor, gp_weight: float = 10.0, shard: tuple[int, int] = (0, 1)
) -> tuple[Tensor, dict[str, Tensor]]:
    """Critic loss and its detached parts: "wasserstein" (mean D(real) - mean D(fake), the
    distance estimate), "gp", "critic_real", "critic_fake". `fake` is detached (critic step only)."""
    fake = fake.detach()
    d_real = critic(real).float().mean()
    d_fake = critic(fake).float().mean()
    gp = gradient_penalty(critic, real, fake, shard)
    loss = (d_fake - d_real) / 2 + gp_weight * gp
    parts = {
        "wasserstein": (d_real - d_fake).detach(),
        "gp": gp.detach(),
        "critic_real": d_real.detach(),
        "critic_fake": d_fake.detach(),
    }
    return loss, parts
