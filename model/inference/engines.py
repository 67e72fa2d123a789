"""Who runs a generator's forward pass on a CPU: torch (the reference), ONNX Runtime or OpenVINO.

The other two run the exported ONNX graph (export.py) and are called like the torch module, with
(1, C, H, W) tensors, so tiling, the ensemble, exposure normalisation and the dark pass (inference.py)
wrap them unchanged. On the 2-core EPYC with AVX512-BF16, one branch of the small generator on a whole
1280x720 image took torch float32 2.47 s, torch bf16 0.88 s, ONNX Runtime float32 0.91 s, OpenVINO
float32 0.72 s and OpenVINO bf16 0.31 s (STACK_NOTES.md; docs/engines.md).
"""
from __future__ import annotations


import numpy as np
import torch
from torch import Tensor, nn

from admc.common.layout import ENGINE_CHOICES, ENGINES
from admc.errors import AdmcError

from ..precision import resolve_precision
from .export import generator_graph

class EngineError(AdmcError, ValueError):
    """An engine that does not exist, is not installed, or cannot run as asked (device, precision)."""


def resolve_engine(name: str, device: torch.device) -> str:
    """The engine `name` asks for on `device`: "auto" is OpenVINO on a CPU (the fastest there, at torch's
    scores: docs/engines.md) and torch on a GPU."""
    if name == "auto":
        return "openvino" if device.type == "cpu" else "torch"
    return name


def check_engine(engine: str, device: torch.device, dtype: torch.dtype) -> None:
    """Refuse what an engine cannot do: an unknown name, a GPU for the CPU engines, bf16 in ONNX Runtime
    (its CPU kernels have no bf16 convolutions)."""
    if engine not in ENGINES:
        raise EngineError(f"engine {engine!r}: not one of {', '.join(ENGINE_CHOICES)}")
    if engine != "torch" and device.type != "cpu":
        raise EngineError(f"engine {engine!r} runs on the CPU only; device {device} needs engine 'torch'")
    if engine == "onnxruntime" and dtype != torch.float32:
        raise EngineError("engine 'onnxruntime' runs float32 only (no bf16 convolutions on the CPU)")


class OnnxGenerator:
    """An exported generator graph under ONNX Runtime or OpenVINO, called as `(noisy, features[, base])`
    with float tensors on the CPU; returns the float32 output tensor. With `noise_input` the features'
    last channel is the noise map, which the graph takes as an input of its own (export.input_names)."""

    def __init__(self, graph: bytes, engine: str, dtype: torch.dtype, noise_input: bool = False) -> None:
        self.engine = engine
        self.noise_input = noise_input
        if engine == "onnxruntime":
            import onnxruntime

            options = onnxruntime.SessionOptions()
            options.intra_op_num_threads = torch.get_num_threads()
            self._session = onnxruntime.InferenceSession(graph, options, providers=["CPUExecutionProvider"])
            self._names = [i.name for i in self._session.get_inputs()]
        else:
            import openvino

            precision = "bf16" if dtype == torch.bfloat16 else "f32"
            core = openvino.Core()
            self._compiled = core.compile_model(
                core.read_model(graph), "CPU", {"INFERENCE_PRECISION_HINT": precision, "PERFORMANCE_HINT": "LATENCY",
                                   "INFERENCE_NUM_THREADS": torch.get_num_threads()})
            self._request = self._compiled.create_infer_request()

    def __call__(self, *inputs: Tensor) -> Tensor:
        if self.noise_input:  # (noisy, features + noise[, base]) -> (noisy, features, noise[, base])
            noisy, features, *base = inputs
            inputs = (noisy, features[:, :-1], features[:, -1:], *base)
        arrays = [np.ascontiguousarray(t.detach().float().cpu().numpy()) for t in inputs]
        if self.engine == "onnxruntime":
            out = self._session.run(None, dict(zip(self._names, arrays)))[0]
        else:
            out = self._request.infer(arrays, share_inputs=True)[0]
        return torch.from_numpy(np.array(out, dtype=np.float32))


def default_precision(engine: str, device: torch.device) -> torch.dtype:
    """An engine's precision when none is asked for: float32 in ONNX Runtime, else as torch would pick
    (bf16 on CUDA and on CPUs with AVX512-BF16 or AMX: precision.resolve_precision)."""
    return torch.float32 if engine == "onnxruntime" else resolve_precision("auto", device)


def onnx_generators(generators: dict[str, nn.Module], engine: str, dtype: torch.dtype) -> dict[str, OnnxGenerator]:
    """Each generator exported to ONNX and loaded into `engine`, in memory (no file is written)."""
    return {branch: OnnxGenerator(generator_graph(generator), engine, dtype,
                                  getattr(getattr(generator, "config", None), "noise_input", False))
            for branch, generator in generators.items()}
