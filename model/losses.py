"""Generator and WGAN-GP critic losses, weighted as in the authors' code.

Generator: l1_weight * L1 + adv_weight * (-mean D(fake)), 1 : 5e-3 (the paper's 200:1).
Critic: (mean D(fake) - mean D(real)) / 2 + gp_weight * GP. The 1/2 on the Wasserstein term is the
authors' (it averages their "real" and "fake" loss terms); the penalty is not halved.
All losses are computed in float32, whatever precision the networks ran in.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


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


def generator_loss(fake: Tensor, real: Tensor, critic_fake: Tensor | None, l1_weight: float = 1.0,
                   adv_weight: float = 5e-3, adversarial: bool = True, l1_floor: float = 1.0
                   ) -> tuple[Tensor, dict[str, Tensor]]:
    """Total generator loss and its detached parts ("l1", and "adversarial" when on).

    `critic_fake` is D(fake) with the graph to the generator kept; `adversarial=False` is the
    paper's "L1 only" ablation, and then `critic_fake` may be None. The L1 term compares
    log_floor(., l1_floor) of both (1.0: the networks' own log1p domain).
    """
    if fake.shape != real.shape:
        raise ValueError(f"generator_loss: fake {tuple(fake.shape)} and real {tuple(real.shape)} differ in shape")
    l1 = F.l1_loss(log_floor(fake.float(), l1_floor), log_floor(real.float(), l1_floor))
    parts = {"l1": l1.detach()}
    if not adversarial:
        return l1_weight * l1, parts
    if critic_fake is None:
        raise ValueError("generator_loss: critic_fake is required when adversarial=True")
    adv = -critic_fake.float().mean()
    parts["adversarial"] = adv.detach()
    return l1_weight * l1 + adv_weight * adv, parts


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
        alpha = alpha[rank * n:(rank + 1) * n]
        interpolates = (alpha * real32 + (1 - alpha) * fake32).requires_grad_(True)
        scores = critic(interpolates).float()
        (grad,) = torch.autograd.grad(scores.sum(), interpolates, create_graph=True)
        # The tiny epsilon keeps the norm's gradient finite where grad is exactly 0.
        norm = torch.sqrt(grad.flatten(1).pow(2).sum(dim=1) + 1e-12)
        return (norm - 1).pow(2).mean()


def critic_loss(critic: nn.Module, real: Tensor, fake: Tensor, gp_weight: float = 10.0,
                shard: tuple[int, int] = (0, 1)) -> tuple[Tensor, dict[str, Tensor]]:
    """Critic loss and its detached parts: "wasserstein" (mean D(real) - mean D(fake), the
    distance estimate), "gp", "critic_real", "critic_fake". `fake` is detached (critic step only)."""
    fake = fake.detach()
    d_real = critic(real).float().mean()
    d_fake = critic(fake).float().mean()
    gp = gradient_penalty(critic, real, fake, shard)
    loss = (d_fake - d_real) / 2 + gp_weight * gp
    parts = {"wasserstein": (d_real - d_fake).detach(), "gp": gp.detach(),
             "critic_real": d_real.detach(), "critic_fake": d_fake.detach()}
    return loss, parts
