"""The CFM denoiser of one branch (diffuse or specular) and its ablation variants.

Architecture as in the authors' code (SFTGAN-style): a head conv, a body of residual blocks whose
convs are preceded by conditioned feature modulation (CFM) driven by a shared EncoderNet, a global
skip from the head over the body, and a tail ending in ReLU (targets are log1p radiance, >= 0).
The `mode` switch builds the paper's ablations (Fig. 12) from the same code; `base = "oidn"` builds the
admc+oidn refiner, which corrects OIDN's output instead of denoising the noisy input.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .encoder import EncoderNet, conv3x3
from .settings import ModelSettings

COLOR_CHANNELS = 3


def _condition_net(cond_channels: int, channels: int, layers: int) -> nn.Module:
    """The 1x1 conv net that maps the condition map to one modulation (gamma or beta) map: the paper's two
    layers, or one (at full resolution they are a third of the small generator's time in OpenVINO:
    docs/results/2026-12-03-slim-generator.md)."""
    if layers == 1:
        return nn.Conv2d(cond_channels, channels, 1)
    return nn.Sequential(
        nn.Conv2d(cond_channels, cond_channels, 1),
        nn.LeakyReLU(0.1, inplace=True),
        nn.Conv2d(cond_channels, channels, 1),
    )


class CFMLayer(nn.Module):
    """Conditioned feature modulation: x * (gamma + 1) + beta, gamma and beta computed per pixel.

    gamma is applied as 1 + scale so a zero scale net output is the identity (the authors' choice,
    which also makes a freshly initialised, small-weight network start near the identity).
    """

    def __init__(
        self, channels: int, cond_channels: int, use_scale: bool = True, use_shift: bool = True, layers: int = 2
    ) -> None:
        super().__init__()
        if not (use_scale or use_shift):
            raise ValueError("CFMLayer needs a scale net, a shift net or both")
        self.scale = _condition_net(cond_channels, channels, layers) if use_scale else None
        self.shift = _condition_net(cond_channels, channels, layers) if use_shift else None

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        if self.scale is not None:
            x = x * (self.scale(cond) + 1)
        if self.shift is not None:
            x = x + self.shift(cond)
        return x


class ResidualBlock(nn.Module):
    """[CFM] -> conv3x3 -> ReLU -> [CFM] -> conv3x3, out = x + f. No batch norm (as in EDSR/SFTGAN).
    Given one CFM layer, only the first conv's input is modulated."""

    def __init__(self, channels: int, cfm: tuple[CFMLayer, ...] | None) -> None:
        super().__init__()
        self.cfm = nn.ModuleList(cfm) if cfm is not None else None
        self.conv1 = conv3x3(channels, channels)
        self.conv2 = conv3x3(channels, channels)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: Tensor, cond: Tensor | None) -> Tensor:
        f = self.cfm[0](x, cond) if self.cfm is not None else x
        f = self.relu(self.conv1(f))
        f = self.cfm[1](f, cond) if self.cfm is not None and len(self.cfm) > 1 else f
        return x + self.conv2(f)


def scaled_kaiming_(module: nn.Module, scale: float) -> None:
    """Kaiming normal (fan-in) init of every conv and linear layer, weights times `scale`, zero biases.

    The authors use scale 0.1 for the generator: a deep residual stack then starts close to the
    identity and trains stably without normalisation layers.
    """
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.kaiming_normal_(m.weight, a=0.0, mode="fan_in")
            with torch.no_grad():
                m.weight.mul_(scale)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def conv_radius(module: nn.Module) -> int:
    """Sum of the spatial radii of every Conv2d in `module` (all of them lie on one chain)."""
    return sum((m.kernel_size[0] // 2) * m.dilation[0] for m in module.modules() if isinstance(m, nn.Conv2d))


def light_within(noisy: Tensor, radius: int) -> Tensor:
    """(N, 1, H, W) bool: is any channel of `noisy` nonzero within `radius` pixels (a square window)?

    A dilation of the "nonzero" map, separably, by OR-ing shifted views of a one-channel bool map: on a
    CPU about 8x faster than max pooling, which also computes indices. An ONNX export traces the loops
    into one image size, so there it is the same dilation as max pooling, which keeps any size.
    """
    lit = (noisy != 0).any(dim=1, keepdim=True)
    if torch.onnx.is_in_onnx_export():
        window = 2 * radius + 1
        grown = F.max_pool2d(lit.float(), (1, window), stride=1, padding=(0, radius))
        return F.max_pool2d(grown, (window, 1), stride=1, padding=(radius, 0)) > 0
    for dim in (3, 2):
        size = lit.shape[dim]
        grown = lit.clone()
        for shift in range(1, min(radius, size - 1) + 1):
            grown.narrow(dim, shift, size - shift).logical_or_(lit.narrow(dim, 0, size - shift))
            grown.narrow(dim, 0, size - shift).logical_or_(lit.narrow(dim, shift, size - shift))
        lit = grown
    return lit


class Generator(nn.Module):
    """One branch's denoiser: `forward(noisy, features)` -> denoised, same (N, 3, H, W) shape.

    Fully convolutional with same-size (replicate-padded) convs everywhere, so any H and W work. The
    authors' network has no skip from the input to the output; `input_skip` adds one (see
    ModelSettings). This class is the paper's full-resolution body; backbones.build_generator picks
    the backbone a config names.

    A refiner (`config.refines`) is called as `forward(noisy, features, base)`: the head sees the
    base (OIDN's output, same log domain as noisy), the EncoderNet sees features + noisy, and the tail's
    last conv starts at zero, so an untrained refiner returns the base exactly. That conv learns in the
    body group from the first step: held back with the head and tail until head_tail_start_step, it
    would block every gradient before it. (A zero gain on a small correction instead sat at the
    saddle where both are small: after 1500 pretraining steps the refiner still equalled OIDN.)
    """

    alignment = 1
    """Tiles must start at multiples of this (1: the network is equivariant to any shift)."""

    def __init__(self, config: ModelSettings = ModelSettings()) -> None:
        config.check()
        super().__init__()
        self.config = config
        c = config.channels
        f = config.feature_channels
        in_channels = COLOR_CHANNELS + f if config.mode == "concat" else COLOR_CHANNELS
        encoder_in = f + COLOR_CHANNELS if config.refines else f
        self.encoder = (
            EncoderNet(config.encoder_channels, config.cond_channels, encoder_in) if config.modulated else None
        )
        self.head = conv3x3(in_channels, c)
        self._build_body()
        self.tail = nn.Sequential(
            conv3x3(c, c),
            nn.ReLU(inplace=True),
            conv3x3(c, COLOR_CHANNELS),
            nn.ReLU(inplace=True),
        )
        scaled_kaiming_(self, 0.1)
        if config.refines:
            nn.init.zeros_(self.tail[-2].weight)
            nn.init.zeros_(self.tail[-2].bias)
        self.gate_radius = self.receptive_radius()

    def _build_body(self) -> None:
        c = self.config.channels
        self.blocks = nn.ModuleList(ResidualBlock(c, self._block_cfms(c)) for _ in range(self.config.blocks))
        self.body_cfm = self._cfm(c) if self.config.modulated else None
        self.body_conv = conv3x3(c, c)

    def _cfm(self, channels: int) -> CFMLayer:
        mode = self.config.mode
        return CFMLayer(
            channels,
            self.config.cond_channels,
            use_scale=mode in ("cfm", "scale"),
            use_shift=mode in ("cfm", "shift"),
            layers=self.config.condition_layers,
        )

    def _block_cfms(self, channels: int) -> tuple[CFMLayer, ...] | None:
        """A residual block's CFM layers (config.cfm_per_block of them), or None without modulation."""
        if not self.config.modulated:
            return None
        return tuple(self._cfm(channels) for _ in range(self.config.cfm_per_block))

    def receptive_radius(self) -> int:
        """How many pixels away an input can still change an output pixel (the denoiser's tile halo and
        how far the darkness gate looks).

        Every spatial conv is 3x3 (radius 1): head 1, two per residual block, body conv 1, tail 2. The
        encoder's one 3x3 conv runs beside the head and meets the image path at the first CFM layer, so
        it adds max(head, encoder) rather than both. Paper config (16 blocks): 1 + 32 + 1 + 2 = 36, a
        73x73 receptive field. The CFM condition nets are 1x1 and add nothing.
        """
        encoder = conv_radius(self.encoder) if self.encoder is not None else 0
        after_head = sum(conv_radius(b) for b in self.blocks) + conv_radius(self.body_conv) + conv_radius(self.tail)
        return max(conv_radius(self.head), encoder) + after_head

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Split for the authors' optimiser: the conditioned body and encoder ("body", 5x LR) and
        the head and tail ("head_tail", base LR, frozen early in training)."""
        outer = {id(p) for m in (self.head, self.tail) for p in m.parameters()}
        if self.config.refines:
            outer -= {id(p) for p in self.tail[-2].parameters()}
        return {
            "body": [p for p in self.parameters() if id(p) not in outer],
            "head_tail": [p for p in self.parameters() if id(p) in outer],
        }

    def _check_inputs(self, noisy: Tensor, features: Tensor | None, base: Tensor | None) -> None:
        if noisy.ndim != 4 or noisy.shape[1] != COLOR_CHANNELS:
            raise ValueError(f"Generator: noisy must be (N, {COLOR_CHANNELS}, H, W), got {tuple(noisy.shape)}")
        if self.config.refines != (base is not None):
            raise ValueError(
                f"Generator (base {self.config.base!r}): "
                + ("the base image (OIDN's output) is required" if self.config.refines else "takes no base image")
            )
        if base is not None and base.shape != noisy.shape:
            raise ValueError(f"Generator: base must match noisy {tuple(noisy.shape)}, got {tuple(base.shape)}")
        if self.config.mode == "none":
            return
        if features is None:
            raise ValueError(f"Generator (mode {self.config.mode!r}): features are required")
        expected = (noisy.shape[0], self.config.feature_channels, *noisy.shape[2:])
        if tuple(features.shape) != expected:
            raise ValueError(f"Generator: features must be {expected} to match noisy, got {tuple(features.shape)}")

    def forward(self, noisy: Tensor, features: Tensor | None = None, base: Tensor | None = None) -> Tensor:
        """`features` (normal, depth, albedo; 7 channels, then the noise map with config.noise_input) may be
        omitted only in mode "none"; `base` is given exactly when the generator refines (config.refines)."""
        self._check_inputs(noisy, features, base)
        # What the output corrects: the noisy input, or a refiner's base (which sees the noisy input
        # through the encoder instead).
        start = noisy if base is None else base
        x = torch.cat([noisy, features], dim=1) if self.config.mode == "concat" else start
        if self.encoder is None:
            cond = None
        else:
            cond = self.encoder(features if base is None else torch.cat([features, noisy], dim=1))
        out = self._body(self.head(x), cond)
        # Predict a correction of the (log-domain) start with input_skip (always for a refiner): an
        # untrained network passes it through, so short CPU trainings improve on it instead of re-learning it.
        skip = self.config.input_skip or self.config.refines
        out = self.tail[:-1](out) if skip else self.tail(out)
        # Darkness gate: where no input radiance lies within the receptive radius the network sees no
        # light at all, yet its biases and the CFM shift of the features still add a constant (a tint
        # over a black background). Such pixels keep their start (zero, or the base): this hides no light it saw.
        out = torch.where(light_within(noisy, self.gate_radius), out, 0.0)
        return torch.relu(start + out) if skip else out

    def _body(self, head: Tensor, cond: Tensor | None) -> Tensor:
        f = head
        for block in self.blocks:
            f = block(f, cond)
        if self.body_cfm is not None:
            f = self.body_cfm(f, cond)
        return head + self.body_conv(f)
