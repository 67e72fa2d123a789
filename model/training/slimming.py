"""A slimmer generator fitted to a trained full one, layer by layer, by least squares: the start of a
fine-tune that already computes nearly what the full network did (scripts/slim_weights.py).

"Slimmer" is model.cfm_per_block = 1 (a residual block modulates only its first conv's input) and/or
model.condition_layers = 1 (each CFM condition net is one 1x1 conv): the same receptive field, 14 instead
of 40 full-resolution 1x1 convs in the small generator. Every layer the two share is copied. A one-layer
condition net becomes the affine map closest to the two-layer net over real condition maps. Where a block
loses its second CFM layer, its second conv is refitted so that the block's output matches the full
block's on the same input; blocks are fitted in order on the slim network's own activations, so each
corrects what the one before got wrong, and the body's last conv likewise.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..nets.generator import CFMLayer, Generator

PIXELS = 200_000
"""Pixels drawn for each least-squares fit (more than enough for at most 145 unknowns per output)."""


def affine_fit(inputs: Tensor, targets: Tensor) -> tuple[Tensor, Tensor]:
    """(weight (m, k), bias (m,)) minimising |inputs @ weight.T + bias - targets|^2 over rows, in float64."""
    x = torch.cat([inputs.double(), torch.ones(len(inputs), 1, dtype=torch.float64)], dim=1)
    solution = torch.linalg.lstsq(x, targets.double(), driver="gelsd").solution
    return solution[:-1].T.to(inputs.dtype), solution[-1].to(inputs.dtype)


def pixels(t: Tensor, index: Tensor) -> Tensor:
    """(N, C, H, W) -> (len(index), C): the channel vectors at flat positions `index`."""
    return t.permute(0, 2, 3, 1).reshape(-1, t.shape[1])[index]


def fit_condition_net(slim: nn.Conv2d, full: nn.Module, cond: Tensor, index: Tensor) -> None:
    """Set a one-layer condition net to the affine map closest to the full one on these condition maps."""
    weight, bias = affine_fit(pixels(cond, index), pixels(full(cond), index))
    slim.weight.copy_(weight[:, :, None, None])
    slim.bias.copy_(bias)


def fit_conv3x3(conv: nn.Conv2d, inputs: Tensor, targets: Tensor, index: Tensor) -> None:
    """Set a replicate-padded 3x3 conv to the one closest to mapping `inputs` to `targets` at `index`."""
    patches = F.unfold(F.pad(inputs, (1, 1, 1, 1), mode="replicate"), 3)  # (N, C*9, H*W), channel-major
    columns = patches.permute(0, 2, 1).reshape(-1, patches.shape[1])[index]
    weight, bias = affine_fit(columns, pixels(targets, index))
    conv.weight.copy_(weight.reshape(conv.weight.shape))
    conv.bias.copy_(bias)


def fit_cfm(slim: CFMLayer, full: CFMLayer, cond: Tensor, index: Tensor) -> None:
    """Fit each one-layer condition net of `slim` that replaces a two-layer one of `full` (condition nets of
    the same shape were copied with the other shared layers)."""
    for name in ("scale", "shift"):
        slim_net, full_net = getattr(slim, name), getattr(full, name)
        if isinstance(slim_net, nn.Conv2d) and not isinstance(full_net, nn.Conv2d):
            fit_condition_net(slim_net, full_net, cond, index)


@torch.no_grad()
def slim_generator(full: Generator, slim: Generator, batch: dict[str, Tensor], seed: int) -> None:
    """Fit `slim` to `full` on one batch of patches (see the module docstring)."""
    slim.load_state_dict(full.state_dict(), strict=False)  # the shared layers; the rest are fitted below
    noisy, features, base = batch["noisy"], batch["features"], batch.get("base")
    start = noisy if base is None else base
    cond = full.encoder(features if base is None else torch.cat([features, noisy], dim=1))
    n, _, h, w = noisy.shape
    index = torch.randperm(n * h * w, generator=torch.Generator().manual_seed(seed))[:PIXELS]
    x = slim.head(start)
    for full_block, slim_block in zip(full.blocks, slim.blocks):
        fit_cfm(slim_block.cfm[0], full_block.cfm[0], cond, index)
        if len(slim_block.cfm) < len(full_block.cfm):
            f = slim_block.relu(slim_block.conv1(slim_block.cfm[0](x, cond)))
            fit_conv3x3(slim_block.conv2, f, full_block(x, cond) - x, index)
        else:
            fit_cfm(slim_block.cfm[1], full_block.cfm[1], cond, index)
        x = slim_block(x, cond)
    fit_cfm(slim.body_cfm, full.body_cfm, cond, index)
    fit_conv3x3(slim.body_conv, slim.body_cfm(x, cond), full.body_conv(full.body_cfm(x, cond)), index)
