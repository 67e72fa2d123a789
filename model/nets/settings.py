"""The networks' shape: the `[model]` section of a run config, and what the networks are built from.

One dataclass for both: a checkpoint records these fields, training and inference build their generators
and critics from them, and the CLI and config checks read them without importing torch (about 2 s of every
`admc-pipe` start, `--help` included). The defaults are the paper's scale (the generator ~1.53 M
parameters, the critic ~14.5 M).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from admc.common.layout import BASES, N_FEATURES

from ..checks import positive_ints, require

# "cfm": full model; "none": no auxiliary features; "concat": features concatenated to the input;
# "shift": CFM with beta only (gamma fixed to 1); "scale": CFM with gamma only (beta fixed to 0).
MODES = ("cfm", "none", "concat", "shift", "scale")
MODULATED_MODES = ("cfm", "shift", "scale")
# "residual": the paper's body of residual blocks at full resolution; "unet": the same CFM residual
# blocks on a multi-scale body (model/nets/unet.py), which sees far more pixels at the same cost.
# backbones.py maps each name to its class.
BACKBONES = ("residual", "unet")
NORMS = ("none", "layer", "batch")
DOWNSAMPLING = 32
"""The critic's five stride-2 convs: its patch size must be a multiple of this."""


@dataclass(frozen=True)
class ModelSettings:
    """Generator and critic architecture of each branch (both branches share it)."""

    channels: int = 64  # generator feature channels
    blocks: int = 16  # CFM residual blocks
    cond_channels: int = 32  # EncoderNet output = condition map channels
    encoder_channels: int = 128  # EncoderNet hidden channels
    mode: str = "cfm"  # cfm | none | concat | shift | scale (the paper's ablations)
    critic_channels: int = 64  # critic base width (VGG-128: 64)
    critic_norm: str = "layer"  # none | layer | batch (batch = the authors' choice)
    input_skip: bool = False  # admc option: out = ReLU(noisy + tail), so training starts at the identity
    # (the authors': no skip)
    backbone: str = "residual"  # residual (the paper's full-resolution body) | unet (multi-scale, model/nets/unet.py)
    levels: int = 3  # unet: resolution halvings; `blocks` then run at 1/2^levels
    base: str = "noisy"  # noisy (the paper's denoiser) | oidn | oidn-fast (admc+oidn: out = ReLU(OIDN +
    # tail), the tail's last conv starting at 0; oidn-fast runs OIDN fast on the
    # specular branch: layout.BASE_QUALITIES)
    noise_input: bool = False  # the EncoderNet also reads the branch's per-pixel noise level, from the
    # renders' variance buffers (transforms.noise_forward): inputs need *_var layers
    cfm_per_block: int = 2  # CFM layers per residual block: 2 (the paper's) | 1 (before its first conv only)
    condition_layers: int = 2  # 1x1 convs per CFM condition net: 2 (the paper's, 1x1 -> LReLU -> 1x1) | 1

    def check(self) -> None:
        """Raise SettingError("<field>: <problem>") for the first field out of range (the networks check
        the settings they are built from; the config loader names the field `model.<field>`)."""
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
        require(
            not self.refines or self.modulated,
            "base",
            f"{self.base!r} needs a mode of {MODULATED_MODES} (the noisy radiance reaches the refiner through "
            f"its EncoderNet), got mode {self.mode!r}",
        )

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

    @classmethod
    def from_saved(cls, saved: dict) -> "ModelSettings":
        """Settings recorded in a checkpoint or weights file; keys added since (e.g. backbone) take the
        value that reproduces what older files computed, which is the field's default."""
        return cls(**{**{f.name: f.default for f in fields(cls)}, **saved})
