"""The "VGG 128" WGAN critic of one branch.

Five stride-2 stages take a square patch down by 32 (128 -> 4), then two linear layers give one
unbounded score per sample. The authors used BatchNorm; admc defaults to a per-sample layer norm
because the WGAN-GP penalty is defined per sample and BatchNorm couples the samples of a batch.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..checks import require
from .generator import scaled_kaiming_
from .settings import DOWNSAMPLING, ModelSettings

HIDDEN_UNITS = 100


def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "layer":
        # GroupNorm with one group = layer norm over (C, H, W) per sample, per-channel affine,
        # independent of the spatial size.
        return nn.GroupNorm(1, channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    return nn.Identity()


class Critic(nn.Module):
    """conv3x3 3->b, LReLU; conv4x4/s2 b->b; then (conv3x3 s1, conv4x4 s2) at 2b, 4b, 8b, 8b;
    each conv after the first with norm and LReLU(0.2); Linear(8b*(P/32)^2, 100), LReLU, Linear(100, 1).
    b is `critic_channels` of the model settings, the norm `critic_norm`, P the `patch_size` it scores."""

    def __init__(self, config: ModelSettings = ModelSettings(), patch_size: int = 128) -> None:
        config.check()
        require(
            type(patch_size) is int and patch_size >= DOWNSAMPLING and patch_size % DOWNSAMPLING == 0,
            "patch_size",
            f"must be a positive multiple of {DOWNSAMPLING}, got {patch_size!r}",
        )
        super().__init__()
        self.config, self.patch_size = config, patch_size
        b, norm = config.critic_channels, config.critic_norm
        layers: list[nn.Module] = [nn.Conv2d(3, b, 3, padding=1), nn.LeakyReLU(0.2, inplace=True)]
        layers += self._stage(b, b, 4, 2, norm)
        previous = b
        for width in (2 * b, 4 * b, 8 * b, 8 * b):
            layers += self._stage(previous, width, 3, 1, norm)
            layers += self._stage(width, width, 4, 2, norm)
            previous = width
        self.features = nn.Sequential(*layers)
        side = patch_size // DOWNSAMPLING
        self.classifier = nn.Sequential(
            nn.Linear(previous * side * side, HIDDEN_UNITS),
            nn.LeakyReLU(0.2, inplace=True),
            nn.Linear(HIDDEN_UNITS, 1),
        )
        scaled_kaiming_(self, 1.0)  # the authors' critic: plain Kaiming fan-in

    @staticmethod
    def _stage(c_in: int, c_out: int, kernel: int, stride: int, norm: str) -> list[nn.Module]:
        return [
            nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=1),
            _norm(norm, c_out),
            nn.LeakyReLU(0.2, inplace=True),
        ]

    def forward(self, x: Tensor) -> Tensor:
        """(N, 3, P, P) -> (N, 1) scores; P must be the configured patch size (the linear layer fixes it)."""
        p = self.patch_size
        if x.ndim != 4 or tuple(x.shape[1:]) != (3, p, p):
            raise ValueError(f"Critic: input must be (N, 3, {p}, {p}), got {tuple(x.shape)}")
        return self.classifier(torch.flatten(self.features(x), 1))
