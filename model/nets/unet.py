"""A multi-scale CFM generator: the paper's conditioned residual blocks on a U-Net-shaped body.

At 4 spp a pixel needs information from many pixels around it. The paper's full-resolution body sees
73x73 pixels with 16 blocks, the small CPU model (4 blocks) 23x23. Halving the resolution `levels`
times lets each block at level l see 2^l times further at a quarter of the cost per level, so the
same budget reaches hundreds of pixels. The EncoderNet's condition map modulates every scale: it is
average-pooled to each level's resolution and drives that level's CFM layers, so the auxiliary
features steer every layer as in the paper.

Shape: head (full resolution, `channels`) -> per level: a CFM residual block, then a stride-2 conv to
the next level's width -> `blocks` CFM residual blocks at 1/2^levels -> per level back up: nearest
upsampling, a 3x3 conv to that level's width, the skip from the way down added, a CFM residual block
-> the paper's tail (and input skip). Widths grow by `channels` per level (16, 32, 48, 64 for the
small model). Inputs whose size is not a multiple of 2^levels are padded at the bottom and right by
repeating their edge, as every conv pads (encoder.conv3x3), and the output cropped back, so any size
works and a flat image stays flat up to its border.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from .encoder import conv3x3
from .generator import Generator, ResidualBlock


class UNetGenerator(Generator):
    """`Generator` with a multi-scale body; forward, tail, input skip and parameter groups as there."""

    @property
    def alignment(self) -> int:
        """Tiles start at multiples of 2^levels: the strided convs then see the same pixel grid."""
        return 2**self.config.levels

    def _build_body(self) -> None:
        c, levels = self.config.channels, self.config.levels
        widths = [c * (level + 1) for level in range(levels + 1)]
        self.down_blocks = nn.ModuleList(ResidualBlock(w, self._block_cfms(w)) for w in widths[:-1])
        self.downs = nn.ModuleList(conv3x3(a, b, stride=2) for a, b in zip(widths, widths[1:]))
        self.bottom = nn.ModuleList(
            ResidualBlock(widths[-1], self._block_cfms(widths[-1])) for _ in range(self.config.blocks)
        )
        self.ups = nn.ModuleList(conv3x3(b, a) for a, b in zip(widths, widths[1:]))
        self.up_blocks = nn.ModuleList(ResidualBlock(w, self._block_cfms(w)) for w in widths[:-1])

    def receptive_radius(self) -> int:
        """An upper bound, in full-resolution pixels, summed along the longest path.

        A 3x3 conv at level l reaches 2^l pixels; the stride-2 conv into level l+1 reaches 2^l; nearest
        upsampling from level l+1 can take a value from up to 2^l pixels further; the head 1, tail 2.
        The condition map pooled to level l enters the path after the image has already travelled
        further than the pool's reach, so it adds nothing to the bound.
        """
        levels, blocks = self.config.levels, self.config.blocks
        down = sum(2 * 2**level + 2**level for level in range(levels))
        bottom = 2 * blocks * 2**levels
        up = sum(2**level + 2**level + 2 * 2**level for level in range(levels))
        return 1 + down + bottom + up + 2

    def _body(self, head: Tensor, cond: Tensor | None) -> Tensor:
        height, width = head.shape[-2:]
        pad_h, pad_w = -height % self.alignment, -width % self.alignment
        f = F.pad(head, (0, pad_w, 0, pad_h), mode="replicate")
        conds = self._pooled(F.pad(cond, (0, pad_w, 0, pad_h), mode="replicate") if cond is not None else None)
        skips = []
        for level, (block, down) in enumerate(zip(self.down_blocks, self.downs)):
            f = block(f, conds[level])
            skips.append(f)
            f = down(f)
        for block in self.bottom:
            f = block(f, conds[-1])
        for level in reversed(range(len(self.ups))):
            f = self.ups[level](F.interpolate(f, scale_factor=2.0, mode="nearest")) + skips[level]
            f = self.up_blocks[level](f, conds[level])
        return head + f[..., :height, :width]

    def _pooled(self, cond: Tensor | None) -> list[Tensor | None]:
        """The condition map at every level's resolution (level 0 = full)."""
        levels = self.config.levels
        if cond is None:
            return [None] * (levels + 1)
        return [cond] + [F.avg_pool2d(cond, 2**level) for level in range(1, levels + 1)]
