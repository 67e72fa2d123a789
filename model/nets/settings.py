"""Network settings: the `[model]` section of a run config, the architecture of both branches.

Shared by training and inference: a checkpoint records these fields, and inference rebuilds its
generators from them. The defaults are the paper's scale.
"""
from __future__ import annotations

from dataclasses import dataclass

from admc.common.layout import BASES

from ..checks import positive_ints, require
from .configs import BACKBONES, MODES, MODULATED_MODES, NORMS, CriticConfig, GeneratorConfig


@dataclass(frozen=True)
class ModelSettings:
    """Generator and critic architecture of each branch (both branches share it)."""

    channels: int = 64            # generator feature channels
    blocks: int = 16              # CFM residual blocks
    cond_channels: int = 32       # EncoderNet output = condition map channels
    encoder_channels: int = 128   # EncoderNet hidden channels
    mode: str = "cfm"             # cfm | none | concat | shift | scale (the paper's ablations)
    critic_channels: int = 64     # critic base width (VGG-128: 64)
    critic_norm: str = "layer"    # none | layer | batch (batch = the authors' choice)
    input_skip: bool = False      # admc option: the generator corrects its input (the authors': no skip)
    backbone: str = "residual"    # residual (the paper's full-resolution body) | unet (multi-scale, model/nets/unet.py)
    levels: int = 3               # unet: resolution halvings; `blocks` then run at 1/2^levels
    base: str = "noisy"           # noisy (the paper's denoiser) | oidn | oidn-fast (admc+oidn: corrects OIDN's
                                  # output; oidn-fast runs OIDN fast on the specular branch: layout.BASE_QUALITIES)
    noise_input: bool = False     # the EncoderNet also reads the branch's per-pixel noise level, from the
                                  # renders' variance buffers (transforms.noise_forward): inputs need *_var layers
    cfm_per_block: int = 2        # CFM layers per residual block: 2 (the paper's) | 1 (before its first conv only)
    condition_layers: int = 2     # 1x1 convs per CFM condition net: 2 (the paper's) | 1

    def check(self) -> None:
        positive_ints(self, ("channels", "blocks", "cond_channels", "encoder_channels", "critic_channels", "levels"))
        require(self.mode in MODES, "mode", f"{self.mode!r} is not one of {MODES}")
        require(self.backbone in BACKBONES, "backbone", f"{self.backbone!r} is not one of {BACKBONES}")
        require(self.critic_norm in NORMS, "critic_norm", f"{self.critic_norm!r} is not one of {NORMS}")
        require(isinstance(self.input_skip, bool), "input_skip", f"must be true or false, got {self.input_skip!r}")
        require(isinstance(self.noise_input, bool), "noise_input", f"must be true or false, got {self.noise_input!r}")
        for key in ("cfm_per_block", "condition_layers"):
            value = getattr(self, key)
            require(type(value) is int and value in (1, 2), key, f"must be 1 or 2, got {value!r}")
        require(self.base in BASES, "base", f"{self.base!r} is not one of {BASES}")
        require(self.base == "noisy" or self.mode in MODULATED_MODES, "base",
                f"{self.base!r} needs a mode of {MODULATED_MODES} (the noisy radiance reaches the refiner through "
                f"its EncoderNet), got mode {self.mode!r}")

    def generator_config(self) -> GeneratorConfig:
        return GeneratorConfig(channels=self.channels, blocks=self.blocks, cond_channels=self.cond_channels,
                               encoder_channels=self.encoder_channels, mode=self.mode, input_skip=self.input_skip,
                               backbone=self.backbone, levels=self.levels, base=self.base,
                               noise_input=self.noise_input, cfm_per_block=self.cfm_per_block,
                               condition_layers=self.condition_layers)

    @classmethod
    def from_saved(cls, saved: dict) -> "ModelSettings":
        """Settings recorded in a checkpoint or weights file; keys added since (e.g. backbone) take the
        value that reproduces what older files computed, which is the field's default."""
        return cls(**{**{f: getattr(cls, f) for f in cls.__dataclass_fields__}, **saved})

    def critic_config(self, patch_size: int) -> CriticConfig:
        return CriticConfig(base_channels=self.critic_channels, norm=self.critic_norm, patch_size=patch_size)
