"""How a FullImageDenoiser runs and what it does around the networks: one settings object."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..symmetry import ENSEMBLE_CODES


@dataclass(frozen=True)
class DenoiserOptions:
    """Every option of a FullImageDenoiser (denoiser.py); the defaults are the plain denoiser on the CPU.

    - `device`: where torch runs (a torch device or its name).
    - `tile`: the largest core edge run at once (None: tiling.default_tile, by device, halo and engine).
    - `overlap`: the halo around each core; None is the largest receptive radius of the two generators, and
      a smaller one is refused (tiles would then differ from the untiled image: seams). Modules that are
      not admc Generators need it given.
    - `dtype`: None = bfloat16 autocast on CUDA and on CPUs with hardware bf16 (AVX512-BF16 or AMX), float32
      elsewhere (precision.resolve_precision); float32 in ONNX Runtime.
    - `compile`: wrap the generators in torch.compile (worth it on GPUs for many images; the first image
      then pays the compile time).
    - `name`: its column in the evaluation tables (None: "admc"; load_denoiser names it after the base the
      weights record); `source`: the weights file it came from (reported next to the tables).
    - `normalize_exposure`: scale dim images up for the networks (exposure.py); False is the measurement
      without it.
    - `dark_pass`: denoise the image a second time at DARK_GAIN times the exposure where it has dark
      regions and take those from it (exposure.dark_weights): up to twice the network time.
    - `ensemble` (1, 2, 4 or 8): average the networks' outputs over that many symmetries of the input
      (symmetry.py), at that many times the network time.
    - `engine`: what runs the generators' forward passes: "torch" (the reference), or on a CPU their
      exported ONNX graphs in "onnxruntime" (float32) or "openvino" (`dtype` as for torch: its
      INFERENCE_PRECISION_HINT); "auto" is openvino on a CPU and torch on a GPU (engines.resolve_engine).
      Everything around the networks is the same in every engine.
    - `keep_resolved`: move the output back toward the input where the input is nearly converged and the
      output departs from it beyond its noise (resolved.py); it needs the variance layers (diffuse_var,
      specular_var) and is skipped without them.
    - `oidn_blend`: {branch: share}: each branch's output becomes share x its own + (1 - share) x OIDN's per-branch
      output (what a fine-tune with train.oidn_blend ships; None: the networks' output alone).
    - `oidn_partner`: {branch: state dict} of OIDN's networks fine-tuned with the weights (train.oidn_minutes):
      the blend takes their output in place of the OIDN library's (None: the library's).
    """

    device: str | torch.device = "cpu"
    tile: int | None = None
    overlap: int | None = None
    dtype: torch.dtype | None = None
    compile: bool = False
    name: str | None = None
    source: str | None = None
    normalize_exposure: bool = True
    dark_pass: bool = False
    ensemble: int = 1
    engine: str = "torch"
    keep_resolved: bool = False
    oidn_blend: dict[str, float] | None = None
    oidn_partner: dict[str, dict] | None = None

    def __post_init__(self) -> None:
        if self.tile is not None and self.tile < 1:
            raise ValueError(f"FullImageDenoiser: tile must be >= 1, got {self.tile}")
        if self.ensemble not in ENSEMBLE_CODES:
            raise ValueError(
                f"FullImageDenoiser: ensemble must be one of {tuple(ENSEMBLE_CODES)}, got {self.ensemble!r}"
            )
