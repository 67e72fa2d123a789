"""Names every layer agrees on: the branches, the feature channels as named slices, the float16 limit."""
from __future__ import annotations

BRANCHES = ("diffuse", "specular")

BASES = ("noisy", "oidn")
"""What a generator starts from and corrects: the noisy radiance (the paper's denoiser) or Intel Open
Image Denoise's output for the same branch (the admc+oidn refiner, which sees the noisy radiance
through its EncoderNet)."""
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
