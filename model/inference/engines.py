"""Who runs a generator's forward pass on a CPU: torch (the reference), ONNX Runtime or OpenVINO.

The other two run the exported ONNX graph (export.py) and are called like the torch module, with
(1, C, H, W) tensors, so tiling, the ensemble, exposure normalisation and the dark pass (inference.py)
wrap them unchanged. On the 2-core EPYC with AVX512-BF16, one branch of the small generator on a whole
1280x720 image took torch float32 2.47 s, torch bf16 0.88 s, ONNX Runtime float32 0.91 s, OpenVINO
float32 0.72 s and OpenVINO bf16 0.31 s (STACK_NOTES.md; docs/engines.md).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterator

import numpy as np
import torch
from torch import Tensor, nn

from admc.common.layout import ENGINE_CHOICES, ENGINES
from admc.errors import AdmcError

from ..precision import resolve_precision
from .onnx_export import generator_graph


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

OPENVINO_STREAMS = 2
"""How many network calls OpenVINO runs at once (`run_together`: an image's tiles, both branches), each on its
share of the threads: the 16-channel layers are too small to keep two threads busy on one call. On the
2-core AVX2 EPYC both networks of a 1280x720 image (four tiles each, float32) took 0.92x the time of
running the tiles in turn at two threads (paired median of 21 alternating runs), for 450 MB more at peak
(each stream holds its own buffers); both branches of a 128x128 image at once took 0.92x too
(docs/engines.md)."""


_openvino_core = None  # the one openvino.Core, once made
_openvino_core_lock = threading.Lock()


def openvino_core():
    """The process's one OpenVINO Core, made at its first use and kept to the end of the process.

    One, never released: each Core makes a CPU plugin of its own, and on Linux that plugin puts an alternate
    signal stack of its own on the thread that makes it (mmap, sigaltstack), puts back the one it found when
    it is released, if its own is still current, and unmaps its own. Two plugins released first-in first-out
    leave the thread's alternate stack pointing at unmapped memory; the next signal that runs a handler on
    that thread (Python's handlers run on the alternate stack: SIGINT, or the SIGCHLD handler torch's
    DataLoader installs) then kills the process with a SIGSEGV that even faulthandler cannot report. That
    was the one-process test suite's segfault (docs/design-decisions.md)."""
    global _openvino_core
    with _openvino_core_lock:
        if _openvino_core is None:
            import openvino

            _openvino_core = openvino.Core()
        return _openvino_core


class OnnxGenerator:
    """An exported generator graph under ONNX Runtime or OpenVINO, called as `(noisy, features[, base])`
    with float tensors on the CPU; returns the float32 output tensor. With `noise_input` the features'
    last channel is the noise map, which the graph takes as an input of its own (export.input_names).

    OpenVINO compiles the graph once for any size and, for each size it is called with, once more for
    that size (the OPENVINO_SIZES last ones are kept): tiles of one image, and images of one size, share
    it. `one_off` runs the graph of any size, for a size that will not come again (the dark pass's crop),
    where compiling for it would cost more than it saves. `run_together` runs several calls at once."""

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
            self._core = openvino_core()
            self._model = self._core.read_model(graph)
            self._threads = torch.get_num_threads()
            self._precision = "bf16" if dtype == torch.bfloat16 else "f32"
            self._any_size = None  # compiled at the first one_off call
            self._sized = {}  # (height, width, streams) -> one infer request per stream

    @property
    def compiled_sizes(self) -> list[tuple[int, int]]:
        """The (height, width) OpenVINO holds a graph compiled for, oldest first."""
        return [size[:2] for size in self._sized] if self.engine == "openvino" else []

    def __call__(self, *inputs: Tensor) -> Tensor:
        arrays = self._arrays(inputs)
        if self.engine == "onnxruntime":
            return _tensor(self._session.run(None, dict(zip(self._names, arrays)))[0])
        request = self._sized_requests(*arrays[0].shape[2:], streams=1)[0]
        return _tensor(request.infer(arrays, share_inputs=True)[0])

    def one_off(self, *inputs: Tensor) -> Tensor:
        """One call in the graph of any size (OpenVINO; ONNX Runtime's graph is of any size anyway)."""
        if self.engine == "onnxruntime":
            return self(*inputs)
        if self._any_size is None:
            self._any_size = self._compile(self._model, streams=1)[0]
        return _tensor(self._any_size.infer(self._arrays(inputs), share_inputs=True)[0])

    def _arrays(self, inputs: tuple[Tensor, ...]) -> list[np.ndarray]:
        if self.noise_input:  # (noisy, features + noise[, base]) -> (noisy, features, noise[, base])
            noisy, features, *base = inputs
            inputs = (noisy, features[:, :-1], features[:, -1:], *base)
        return [np.ascontiguousarray(t.detach().float().cpu().numpy()) for t in inputs]

    def _compile(self, model, streams: int) -> list:
        """`streams` infer requests of `model`, each on threads / streams of the threads. Several streams
        are not pinned to cores: each graph would pin its first stream to the first core, and the two
        branches' graphs, run at once, would share it (1.8x the time of one after the other)."""
        config = {
            "INFERENCE_PRECISION_HINT": self._precision,
            "INFERENCE_NUM_THREADS": self._threads,
            "PERFORMANCE_HINT": "LATENCY" if streams == 1 else "THROUGHPUT",
            **({"NUM_STREAMS": streams, "ENABLE_CPU_PINNING": False} if streams > 1 else {}),
        }
        compiled = self._core.compile_model(model, "CPU", config)
        return [compiled.create_infer_request() for _ in range(streams)]

    def _sized_requests(self, height: int, width: int, streams: int) -> list:
        """The requests of the graph compiled for this size and stream count, made most recent (compiled if
        not held)."""
        key = (height, width, streams)
        requests = self._sized.pop(key, None)
        if requests is None:
            model = self._model.clone()
            model.reshape(
                {i.get_any_name(): [1, i.get_partial_shape()[1].get_length(), height, width] for i in model.inputs}
            )
            requests = self._compile(model, streams)
            if len(self._sized) >= OPENVINO_SIZES:
                self._sized.pop(next(iter(self._sized)))
        self._sized[key] = requests
        return requests


def run_together(calls: list[tuple[Callable, tuple[Tensor, ...]]]) -> Iterator[Tensor]:
    """The outputs of `(generator, inputs)` calls, in order. Where every generator is an OpenVINO graph with
    a thread per stream, OPENVINO_STREAMS calls run at once, each in its generator's graph compiled for its
    size; otherwise the calls run in turn."""
    together = len(calls) > 1 and all(
        isinstance(g, OnnxGenerator) and g.engine == "openvino" and g._threads >= OPENVINO_STREAMS for g, _ in calls
    )
    if not together:
        yield from (generator(*inputs) for generator, inputs in calls)
        return
    running = deque()  # (request, the arrays it reads), oldest first
    try:
        for index, (generator, inputs) in enumerate(calls):
            if len(running) == OPENVINO_STREAMS:
                yield _finished(*running.popleft())
            # the call OPENVINO_STREAMS before this one, the last to use this slot, is finished
            arrays = generator._arrays(inputs)
            request = generator._sized_requests(*arrays[0].shape[2:], OPENVINO_STREAMS)[index % OPENVINO_STREAMS]
            request.start_async(arrays, share_inputs=True)
            running.append((request, arrays))
        while running:
            yield _finished(*running.popleft())
    finally:  # stopped early (an error, a caller that gave up): no request may read freed arrays
        for request, _ in running:
            request.wait()


def _tensor(output: np.ndarray) -> Tensor:
    """An engine's output as a float32 tensor of its own (the engine reuses its output buffer)."""
    return torch.from_numpy(np.array(output, dtype=np.float32))


def _finished(request, arrays: list[np.ndarray]) -> Tensor:
    """The output of a started OpenVINO request, once it is done (`arrays`: its inputs, alive until then)."""
    request.wait()
    return _tensor(request.get_output_tensor(0).data)


def default_precision(engine: str, device: torch.device) -> torch.dtype:
    """An engine's precision when none is asked for: float32 in ONNX Runtime, else as torch would pick
    (bf16 on CUDA and on CPUs with AVX512-BF16 or AMX: precision.resolve_precision)."""
    return torch.float32 if engine == "onnxruntime" else resolve_precision("auto", device)


def onnx_generators(generators: dict[str, nn.Module], engine: str, dtype: torch.dtype) -> dict[str, OnnxGenerator]:
    """Each generator exported to ONNX and loaded into `engine`, in memory (no file is written)."""
    return {
        branch: OnnxGenerator(
            generator_graph(generator), engine, dtype, getattr(getattr(generator, "config", None), "noise_input", False)
        )
        for branch, generator in generators.items()
    }
