"""Names every layer agrees on: the branches, the feature channels as named slices, the float16 limit."""

from __future__ import annotations

BRANCHES = ("diffuse", "specular")

RAW = " raw"
"""Suffix of a fine-tuned OIDN candidate network that learns from the raw references ("diffuse raw"); one
named as its branch learns from the store's targets. Training names them, checkpoints store them by name."""


def branch_of(candidate: str) -> str:
    """The branch a fine-tuned OIDN candidate ("diffuse raw", "specular") denoises."""
    return candidate.removesuffix(RAW)


BASE_QUALITIES = {"oidn": {"diffuse": "high", "specular": "high"}, "oidn-fast": {"diffuse": "high", "specular": "fast"}}
"""The refining bases and the OIDN quality each branch's input is denoised at. OIDN `fast` takes about half
of `high`'s time on a CPU (`balanced` runs as `high` there); on the specular branch, which OIDN denoises
without guides, it costs a refiner about 1 %, on the diffuse branch 5-10 % (docs/results/2026-12-03-fast-bases.md)."""
BASES = ("noisy", *BASE_QUALITIES)
"""What a generator starts from and corrects: the noisy radiance (the paper's denoiser) or Intel Open
Image Denoise's output for the same branch (the admc+oidn refiner, which sees the noisy radiance
through its EncoderNet), at the qualities BASE_QUALITIES names."""
ENSEMBLES = (1, 2, 4, 8)
"""How many symmetries of an input a denoiser may average its outputs over (model/symmetry.py)."""
ENGINES = ("torch", "onnxruntime", "openvino")
"""What may run a denoiser's networks (model/inference/engines.py): torch, or their ONNX graphs on a CPU."""
ENGINE_CHOICES = ("auto", *ENGINES)
"""What a user may ask for: auto picks by device (engines.resolve_engine)."""

FEATURE_CHANNELS = ("normal.X", "normal.Y", "normal.Z", "depth", "albedo.R", "albedo.G", "albedo.B")
"""The feature channels in the authors' order: normal(3), depth(1), albedo(3)."""
N_FEATURES = len(FEATURE_CHANNELS)
NORMAL = slice(0, 3)
DEPTH = slice(3, 4)
ALBEDO = slice(4, 7)

FP16_MAX = 65504.0
"""Largest finite float16: values beyond it would become inf when stored in half precision."""
