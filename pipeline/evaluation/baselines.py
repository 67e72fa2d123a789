"""The methods under test: one small interface, the noisy baseline, Intel Open Image Denoise, timing.

The trained admc model joins the evaluation by implementing `Denoiser` (see model/): the evaluation
only ever calls `denoise` and `synchronize`, and prints `name` and `device`.

NVIDIA's OptiX denoiser joins through Mitsuba (`mi.OptixDenoiser`) where the `cuda_ad_rgb` variant
runs; `optix_unavailable_reason` says why not elsewhere, so a report can state it.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from typing import Protocol, runtime_checkable

import numpy as np

from admc.common import oidn
from admc.common.buffers import BEAUTY, sanitize
from admc.pipeline.render.variants import available_variants


@runtime_checkable
class Denoiser(Protocol):
    name: str  # column name in the tables, e.g. "noisy", "oidn", "admc"
    device: str  # what computes it, e.g. "cpu (AMD EPYC 9R14, 2 threads)", "cuda:0 (NVIDIA H100)"
    # optional: `source`, the weights file a learned denoiser came from (reported with the tables)

    def denoise(self, layers: dict[str, np.ndarray]) -> np.ndarray:
        """(H, W, 3) float32 linear HDR radiance from the render layers of one noisy image."""
        ...

    def synchronize(self) -> None:
        """Wait until all work queued on the device is done (a no-op on CPU), for honest timing."""
        ...


def cpu_description() -> str:
    """'cpu (<model>, N threads)': which CPU produced a timing."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            model = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"cpu ({model}, {threads} threads)"


def noisy_color(layers: dict[str, np.ndarray]) -> np.ndarray:
    """The path tracer's image: diffuse + specular (scenes without specular materials have no specular)."""
    if "diffuse" not in layers:
        raise KeyError(f"render layers lack 'diffuse' (have {', '.join(sorted(layers))})")
    color = np.asarray(layers["diffuse"], dtype=np.float32)
    if "specular" in layers:
        color = color + np.asarray(layers["specular"], dtype=np.float32)
    return color


class NoisyInput:
    """The baseline row: the raw path-traced image, untouched."""

    name = "noisy"

    def __init__(self) -> None:
        self.device = cpu_description()

    def denoise(self, layers: dict[str, np.ndarray]) -> np.ndarray:
        return noisy_color(layers)

    def synchronize(self) -> None:
        pass


def _guided_inputs(layers: dict[str, np.ndarray], who: str) -> tuple[list[np.ndarray], int]:
    """([colour, albedo, normal] sanitised for an albedo+normal guided denoiser, colour values replaced).

    The colour is the beauty (diffuse + specular); each buffer follows its rule in admc.common.buffers
    (HDR modes expect non-negative radiance, and a NaN spreads over the whole receptive field)."""
    colour, counts = sanitize(noisy_color(layers), BEAUTY)
    for name in ("albedo", "normal"):
        if name not in layers:
            raise KeyError(f"{who} needs the {name!r} layer (have {', '.join(sorted(layers))})")
    replaced = counts["nan"] + counts["posinf"] + counts["neginf"]
    return [colour, sanitize(layers["albedo"], "albedo")[0], sanitize(layers["normal"], "normal")[0]], replaced


class OidnDenoiser:
    """Intel Open Image Denoise (pyoidn), HDR mode, with albedo and normal as auxiliary inputs; `prefiltered`:
    OIDN's final-frame route, the guides denoised by OIDN itself first and the colour then with cleanAux (its
    large network at quality high).

    Inputs are sanitised first (`_guided_inputs`); `last_sanitized` counts the colour values replaced
    in the latest call.
    device="cpu" runs on NumPy arrays; "cuda" or "cuda:N" runs through CUDA torch tensors and
    includes the host<->device copies in its time (untested here: this machine has no GPU).
    pyoidn keeps one device and filter per process and reuses them across images.
    """

    def __init__(
        self, quality: str = "high", device: str = "cpu", name: str | None = None, prefiltered: bool = False
    ) -> None:
        import pyoidn

        self.quality = oidn.check_quality(quality)
        self.prefiltered = prefiltered
        route = "-prefiltered" if prefiltered else ""
        self.name = name or ("oidn" if quality == "high" else f"oidn-{quality}") + route
        if prefiltered and device != "cpu":
            raise ValueError("OIDN's prefiltered route runs on the CPU device here")
        self.last_sanitized = 0
        self._torch_device = None
        if device == "cpu":
            if not pyoidn.Device.is_cpu_available():
                raise RuntimeError("OIDN has no CPU device on this machine")
            self.device = cpu_description()
        elif device.startswith("cuda"):
            import torch

            if not torch.cuda.is_available():
                raise RuntimeError(f"OIDN device {device!r} asked for, but torch sees no CUDA GPU")
            self._torch_device = torch.device(device)
            index = self._torch_device.index or 0
            if not pyoidn.Device.is_cuda_available(index):
                raise RuntimeError(f"this pyoidn build has no CUDA device backend for GPU {index}")
            self.device = f"cuda:{index} ({torch.cuda.get_device_name(index)})"
        else:
            raise ValueError(f"OIDN device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}")

    def denoise(self, layers: dict[str, np.ndarray]) -> np.ndarray:
        inputs, self.last_sanitized = _guided_inputs(layers, "OIDN")
        if self.prefiltered:
            colour, albedo, normal = inputs
            albedo, normal = oidn.prefilter("albedo", albedo), oidn.prefilter("normal", normal)
            return oidn.denoise(colour, albedo, normal, quality=self.quality, clean_aux=True)
        if self._torch_device is None:
            return oidn.denoise(*inputs, quality=self.quality)
        import torch

        tensors = [torch.from_numpy(a).to(self._torch_device) for a in inputs]
        return oidn.denoise(*tensors, quality=self.quality).cpu().numpy()

    def synchronize(self) -> None:
        if self._torch_device is not None:
            import torch

            torch.cuda.synchronize(self._torch_device)


OPTIX_VARIANT = "cuda_ad_rgb"


def optix_unavailable_reason() -> str | None:
    """None where Mitsuba's OptiX denoiser can run here, else why not (for the report and errors)."""
    import mitsuba as mi

    if OPTIX_VARIANT not in mi.variants():
        return f"this Mitsuba build has no {OPTIX_VARIANT} variant"
    if OPTIX_VARIANT not in available_variants():
        return f"Mitsuba's {OPTIX_VARIANT} variant needs a CUDA GPU and driver, and Dr.Jit finds none here"
    return None


def mitsuba_sensor_normals(view_normals: np.ndarray) -> np.ndarray:
    """admc's view-space normals (x right, y up, z toward the viewer) in Mitsuba's sensor frame
    (x left, y up, z forward), the frame `mi.OptixDenoiser` asks for: a half turn about y."""
    return np.ascontiguousarray(np.asarray(view_normals, dtype=np.float32) * np.float32([-1.0, 1.0, -1.0]))


class OptixDenoiser:
    """NVIDIA OptiX AI denoiser (HDR model, albedo + normal guides) through Mitsuba's `cuda_ad_rgb` variant.

    Inputs are sanitised as for OIDN. OptiX fixes the image size when a denoiser is created, so one
    is kept per size (created by the warm-up run, outside the timed runs). Its time includes the
    host<->device copies, as the CUDA OIDN's does.
    """

    name = "optix"

    def __init__(self) -> None:
        reason = optix_unavailable_reason()
        if reason:
            raise RuntimeError(f"the OptiX denoiser cannot run: {reason}")
        import drjit as dr
        import mitsuba as mi

        self._mi, self._dr = mi, dr
        self._by_size: dict[tuple[int, int], object] = {}
        self.last_sanitized = 0
        self.device = f"cuda ({_gpu_name()}, OptiX via Mitsuba {mi.__version__})"

    def denoise(self, layers: dict[str, np.ndarray]) -> np.ndarray:
        (color, albedo, normals), self.last_sanitized = _guided_inputs(layers, "OptiX")
        normals = mitsuba_sensor_normals(normals)
        mi = self._mi
        previous = mi.variant()
        mi.set_variant(OPTIX_VARIANT)
        try:
            height, width = color.shape[:2]
            denoiser = self._by_size.get((height, width))
            if denoiser is None:
                denoiser = mi.OptixDenoiser(mi.ScalarVector2u(width, height), albedo=True, normals=True)
                self._by_size[(height, width)] = denoiser
            out = denoiser(mi.TensorXf(color), albedo=mi.TensorXf(albedo), normals=mi.TensorXf(normals))
            return np.array(out, dtype=np.float32)
        finally:
            if previous:
                mi.set_variant(previous)

    def synchronize(self) -> None:
        self._dr.sync_thread()


def _gpu_name() -> str:
    """The GPU's name for the report: from torch when it sees CUDA, else from nvidia-smi."""
    try:
        import torch

        if torch.cuda.is_available():
            return torch.cuda.get_device_name(0)
    except ImportError:
        pass
    import subprocess

    try:
        query = subprocess.run(
            ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True, timeout=10
        )
        return query.stdout.splitlines()[0].strip() if query.returncode == 0 and query.stdout else "GPU"
    except (OSError, subprocess.TimeoutExpired):
        return "GPU"


def time_denoiser(
    denoiser: Denoiser, layers: dict[str, np.ndarray], repeats: int = 1, warmup: int = 1
) -> tuple[np.ndarray, float]:
    """(image, seconds): `warmup` untimed runs, then the median of `repeats` synchronised runs.

    Warm-up keeps one-off costs (JIT, weight upload, allocator growth) out of the figure; each timed
    run is bracketed by `synchronize` so queued GPU work is counted where it is spent.
    """
    if repeats < 1 or warmup < 0:
        raise ValueError(f"repeats must be >= 1 and warmup >= 0, got repeats={repeats}, warmup={warmup}")
    for _ in range(warmup):
        denoiser.denoise(layers)
    denoiser.synchronize()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        image = denoiser.denoise(layers)
        denoiser.synchronize()
        times.append(time.perf_counter() - start)
    image = np.asarray(image, dtype=np.float32)
    expected = np.shape(layers["diffuse"])
    if image.shape != expected:
        raise ValueError(f"denoiser {denoiser.name!r} returned shape {image.shape}, expected {expected}")
    return image, statistics.median(times)
