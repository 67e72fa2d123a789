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


OPENVINO_SIZES = 2
"""How many input sizes an OpenVINO generator keeps compiled for their own size: two, a tile and its
transpose (the ensemble's). The small model's graph compiled for one static size ran 1280x720 (tiles of
640) in 0.88x the time of the graph of dynamic size (paired median of 25 alternating runs;
docs/engines.md); compiling for a size takes 0.15-0.2 s, and each holds its own buffers (the process grew
by 180 MB for a 664x384 tile, 500 MB for 1280x720, per branch)."""


class OnnxGenerator:
    """An exported generator graph under ONNX Runtime or OpenVINO, called as `(noisy, features[, base])`
    with float tensors on the CPU; returns the float32 output tensor. With `noise_input` the features'
    last channel is the noise map, which the graph takes as an input of its own (export.input_names).

    OpenVINO compiles the graph once for any size and, for each size it is called with, once more for
    that size (the OPENVINO_SIZES last ones are kept): tiles of one image, and images of one size, share
    it. `one_off` runs the graph of any size, for a size that will not come again (the dark pass's crop),
    where compiling for it would cost more than it saves."""

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

            self._core = openvino.Core()
            self._model = self._core.read_model(graph)
            self._config = {"INFERENCE_PRECISION_HINT": "bf16" if dtype == torch.bfloat16 else "f32",
                            "PERFORMANCE_HINT": "LATENCY", "INFERENCE_NUM_THREADS": torch.get_num_threads()}
            self._any_size = None  # compiled at the first one_off call
            self._sized = {}

    @property
    def compiled_sizes(self) -> list[tuple[int, int]]:
        """The (height, width) OpenVINO holds a graph compiled for, oldest first."""
        return list(self._sized) if self.engine == "openvino" else []

    def __call__(self, *inputs: Tensor) -> Tensor:
        return self._infer(inputs, sized=True)

    def one_off(self, *inputs: Tensor) -> Tensor:
        return self._infer(inputs, sized=False)

    def _infer(self, inputs: tuple[Tensor, ...], sized: bool) -> Tensor:
        if self.noise_input:  # (noisy, features + noise[, base]) -> (noisy, features, noise[, base])
            noisy, features, *base = inputs
            inputs = (noisy, features[:, :-1], features[:, -1:], *base)
        arrays = [np.ascontiguousarray(t.detach().float().cpu().numpy()) for t in inputs]
        if self.engine == "onnxruntime":
            out = self._session.run(None, dict(zip(self._names, arrays)))[0]
        else:
            request = self._sized_request(*arrays[0].shape[2:]) if sized else self._any_size_request()
            out = request.infer(arrays, share_inputs=True)[0]
        return torch.from_numpy(np.array(out, dtype=np.float32))

    def _request(self, model):
        return self._core.compile_model(model, "CPU", self._config).create_infer_request()

    def _any_size_request(self):
        if self._any_size is None:
            self._any_size = self._request(self._model)
        return self._any_size

    def _sized_request(self, height: int, width: int):
        """The request of the graph compiled for this size, made most recent (compiled if not held)."""
        request = self._sized.pop((height, width), None)
        if request is None:
            model = self._model.clone()
            model.reshape({i.get_any_name(): [1, i.get_partial_shape()[1].get_length(), height, width]
                           for i in model.inputs})
            request = self._request(model)
            if len(self._sized) >= OPENVINO_SIZES:
                self._sized.pop(next(iter(self._sized)))
        self._sized[(height, width)] = request
        return request


def default_precision(engine: str, device: torch.device) -> torch.dtype:
    """An engine's precision when none is asked for: float32 in ONNX Runtime, else as torch would pick
    (bf16 on CUDA and on CPUs with AVX512-BF16 or AMX: precision.resolve_precision)."""
    return torch.float32 if engine == "onnxruntime" else resolve_precision("auto", device)


def onnx_generators(generators: dict[str, nn.Module], engine: str, dtype: torch.dtype) -> dict[str, OnnxGenerator]:
    """Each generator exported to ONNX and loaded into `engine`, in memory (no file is written)."""
    return {branch: OnnxGenerator(generator_graph(generator), engine, dtype,
                                  getattr(getattr(generator, "config", None), "noise_input", False))
            for branch, generator in generators.items()}
