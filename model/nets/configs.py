"""The two networks' shape settings, apart from the networks: the CLI and the config checks read them
without importing torch (about 2 s of every `admc-pipe` start, `--help` included)."""
from __future__ import annotations

from dataclasses import dataclass

from admc.common.layout import BASES, N_FEATURES

# "cfm": full model; "none": no auxiliary features; "concat": features concatenated to the input;
# "shift": CFM with beta only (gamma fixed to 1); "scale": CFM with gamma only (beta fixed to 0).
MODES = ("cfm", "none", "concat", "shift", "scale")
MODULATED_MODES = ("cfm", "shift", "scale")
# "residual": the paper's body of residual blocks at full resolution; "unet": the same CFM residual
# blocks on a multi-scale body (model/nets/unet.py), which sees far more pixels at the same cost.
# backbones.py maps each name to its class.
BACKBONES = ("residual", "unet")


@dataclass(frozen=True)
class GeneratorConfig:
    """Size and ablation mode of one branch's generator; the defaults are the paper's (~1.53 M params)."""

    channels: int = 64
    blocks: int = 16
    cond_channels: int = 32
    encoder_channels: int = 128
    mode: str = "cfm"
    input_skip: bool = False  # admc option: out = ReLU(noisy + tail), so training starts at the identity
    backbone: str = "residual"
    levels: int = 3           # unet: times the resolution is halved (blocks then run at 1/2^levels)
    base: str = "noisy"       # "oidn", "oidn-fast": out = ReLU(OIDN + tail), the tail's last conv starting at 0
    noise_input: bool = False  # features carry the branch's noise map as an 8th channel (transforms.noise_forward)
    cfm_per_block: int = 2     # 2: CFM before both convs of a residual block (the paper's); 1: before the first only
    condition_layers: int = 2  # convs per CFM condition net: 2 (the paper's, 1x1 -> LReLU -> 1x1) or 1 (one 1x1)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"GeneratorConfig.mode: {self.mode!r} is not one of {MODES}")
        if self.base not in BASES:
            raise ValueError(f"GeneratorConfig.base: {self.base!r} is not one of {BASES}")
        if self.refines and self.mode not in MODULATED_MODES:
            raise ValueError(f"GeneratorConfig.base {self.base!r} needs a modulated mode {MODULATED_MODES} (the noisy "
                             f"radiance reaches a refiner through its EncoderNet), got mode {self.mode!r}")
        if self.backbone not in BACKBONES:
            raise ValueError(f"GeneratorConfig.backbone: {self.backbone!r} is not one of {BACKBONES}")
        for name in ("channels", "blocks", "cond_channels", "encoder_channels", "levels"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"GeneratorConfig.{name}: must be a positive int, got {value!r}")
        for name in ("cfm_per_block", "condition_layers"):
            value = getattr(self, name)
            if type(value) is not int or value not in (1, 2):
                raise ValueError(f"GeneratorConfig.{name}: must be 1 or 2, got {value!r}")

    @property
    def modulated(self) -> bool:
        return self.mode in MODULATED_MODES

    @property
    def feature_channels(self) -> int:
        """Channels of the `features` the generator is called with: the 7 auxiliary ones [+ the noise map]."""
        return N_FEATURES + int(self.noise_input)

    @property
    def refines(self) -> bool:
        """Whether the generator corrects OIDN's output (given as `base`) rather than the noisy input."""
        return self.base != "noisy"


NORMS = ("none", "layer", "batch")
DOWNSAMPLING = 32  # five stride-2 convs


@dataclass(frozen=True)
class CriticConfig:
    """Width, normalisation and input patch size; the defaults are the paper's (~14.5 M params)."""

    base_channels: int = 64
    norm: str = "layer"
    patch_size: int = 128

    def __post_init__(self) -> None:
        if self.norm not in NORMS:
            raise ValueError(f"CriticConfig.norm: {self.norm!r} is not one of {NORMS}")
        if not isinstance(self.base_channels, int) or self.base_channels < 1:
            raise ValueError(f"CriticConfig.base_channels: must be a positive int, got {self.base_channels!r}")
        if not isinstance(self.patch_size, int) or self.patch_size < DOWNSAMPLING or self.patch_size % DOWNSAMPLING:
            raise ValueError(f"CriticConfig.patch_size: must be a positive multiple of {DOWNSAMPLING}, "
                             f"got {self.patch_size!r}")
