"""EncoderNet: turns the 7 auxiliary feature channels into the 32-channel condition map.

A refiner of OIDN's output (model.base = "oidn") also feeds the noisy radiance (3 more channels) to its
encoder: the image path carries OIDN's estimate, the condition tells it what OIDN discarded.

One encoder per branch is shared by every CFM layer of that branch, so the features are encoded
once per forward pass rather than once per layer. It runs at full resolution (no striding):
CFM modulates per pixel, so the condition must stay aligned with the image.
"""

from __future__ import annotations

from torch import Tensor, nn

from admc.common.layout import N_FEATURES


def conv3x3(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    """The generator's and encoder's same-size 3x3 conv, padding by repeating the edge pixels.

    Zero padding made the image border look like a black frame to every layer, so the output
    differed there from the interior even on a flat image; replicate padding keeps a flat image flat
    up to its border and, unlike reflect padding, works for images one pixel wide.
    """
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, padding_mode="replicate")


class EncoderNet(nn.Module):
    """conv3x3 in->hidden, LReLU(0.1), 3 x [conv1x1 hidden->hidden, LReLU(0.1)], conv1x1 hidden->out."""

    def __init__(self, hidden_channels: int = 128, out_channels: int = 32, in_channels: int = N_FEATURES) -> None:
        super().__init__()
        layers: list[nn.Module] = [
            conv3x3(in_channels, hidden_channels),
            nn.LeakyReLU(0.1, inplace=True),
        ]
        for _ in range(3):
            layers += [nn.Conv2d(hidden_channels, hidden_channels, 1), nn.LeakyReLU(0.1, inplace=True)]
        # No final activation: the condition map may be negative, the CFM nets decide its use.
        layers.append(nn.Conv2d(hidden_channels, out_channels, 1))
        self.layers = nn.Sequential(*layers)

    def forward(self, features: Tensor) -> Tensor:
        return self.layers(features)
