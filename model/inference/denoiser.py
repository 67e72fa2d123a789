"""Denoise whole images of any size with the two trained branches, tile by tile where they are large.

Large images run in tiles so CPU memory stays bounded; tiling.py makes the tiled result equal the
untiled one (no seams).

A refiner (generators with config.base "oidn" or "oidn-fast") first runs OIDN per branch on the whole image
(oidn_base.oidn_bases, as tiling did for its training rows), then corrects OIDN's output tile by tile:
one call, and its time includes OIDN's.

A dim image is scaled up for the networks and its output scaled back, and the dark regions of any
image are taken from a second pass at a higher exposure (exposure.py).
"""
from __future__ import annotations

import contextlib
import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor, nn

from admc.common.buffers import DENOISER_LAYERS, LAYERS, MISSING_LAYERS, sanitize
from admc.common.diff import differing_keys
from admc.common.threads import torch_inline
from admc.errors import AdmcError

from ..nets.backbones import build_generator
from ..nets.generator import Generator
from ..precision import MEMORY_FORMAT, autocast_for, precision_name
from ..symmetry import ENSEMBLE_CODES, apply, undo
from ..transforms import (
    EPS,
    RADIANCE_MAX,
    diffuse_forward,
    diffuse_inverse,
    diffuse_noise,
    features,
    specular_forward,
    specular_inverse,
    specular_noise,
)
from .engines import OnnxGenerator, check_engine, default_precision, onnx_generators, resolve_engine, run_together
from .exposure import DARK_GAIN, dark_weights, exposure_gain
from .oidn_base import oidn_bases
from .resolved import keep_resolved
from .tiling import default_tile, paste, receptive_radius, tile_calls

REQUIRED_LAYERS = ("diffuse", "albedo", "normal")
WHOLE_IMAGE = (slice(None), slice(None))
# Largest log value an input can take; network outputs are clamped to it so the inverse stays finite.
LOG_MAX = {
    "diffuse": float(np.log1p(RADIANCE_MAX / EPS)),
    "specular": float(np.log1p(RADIANCE_MAX)),
}


class MissingVarianceError(AdmcError, KeyError):
    """Weights with model.noise_input were given an input without the variance layers they read."""

    def __str__(self) -> str:  # KeyError's own would quote the message
        return str(self.args[0])


@dataclass
class DenoiseResult:
    """One denoised image, its parts, what was repaired on the way in, and what it cost."""

    image: np.ndarray                    # (H, W, 3) float32 linear HDR: diffuse + specular
    diffuse: np.ndarray                  # (H, W, 3) float32 linear denoised diffuse (albedo re-applied)
    specular: np.ndarray | None          # (H, W, 3) linear specular: denoised, or the input passed through
    branches: tuple[str, ...]            # the branches whose network ran: ("diffuse",) or both
    specular_passed_through: bool        # the input had specular but no specular generator was given
    sanitized: dict[str, dict[str, int]] = field(default_factory=dict)  # layer -> nonzero repair counts
    nonfinite_outputs: int = 0           # network output values that were NaN/Inf (set to 0)
    tiles: int = 1                       # network calls per branch
    network_seconds: float = 0.0         # generator time, synchronised (both branches)
    base_seconds: float = 0.0            # OIDN's time for a refiner's bases (0 for base "noisy")
    exposure_gain: float = 1.0           # the radiance went through the networks times this (exposure.py)
    dark_share: float = 0.0              # mean share of the second pass at DARK_GAIN x that (0: it did not run)
    resolved_share: float = 0.0          # mean weight of the input kept where it was resolved (resolved.py)
    seconds: float = 0.0                 # whole call: sanitising, OIDN, transforms, networks, inverse

    @property
    def notes(self) -> list[str]:
        """Plain sentences for the user about what happened beyond the obvious."""
        notes = []
        for layer, counts in self.sanitized.items():
            what = ", ".join(f"{n} {kind}" for kind, n in counts.items())
            notes.append(f"{layer}: repaired {what} value(s) before denoising")
        if self.specular_passed_through:
            notes.append("specular: no specular network given, the noisy specular was added unchanged")
        if self.nonfinite_outputs:
            notes.append(f"the network produced {self.nonfinite_outputs} non-finite value(s), set to 0")
        if self.exposure_gain != 1.0:
            notes.append(f"a dim image: denoised at {self.exposure_gain:.3g}x its exposure, the output scaled back")
        if self.resolved_share:
            notes.append(f"where the render was already resolved, kept its detail (mean weight of the input "
                         f"{self.resolved_share:.2g})")
        return notes


def _device_description(device: torch.device) -> str:
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return f"{device.type} ({torch.get_num_threads()} threads)"


class FullImageDenoiser:
    """Sanitize -> forward transforms -> diffuse [and specular] generator -> inverse -> linear HDR.

    `diffuse` and `specular` are admc Generators (or any module called as `(noisy, features)`; those
    need an explicit `overlap`). They are moved to `device` and put in eval mode. `tile` is the
    largest core edge run at once (None: tiling.default_tile, by device, halo and engine); `overlap` is the
    halo around each core, by default the largest receptive radius of the two generators, and a
    smaller one is refused (tiles would then differ from the untiled image: seams). `dtype`: None =
    bfloat16 autocast on CUDA and on CPUs with hardware bf16 (AVX512-BF16 or AMX), float32 elsewhere
    (precision.resolve_precision).
    `compile` wraps the generators in torch.compile (worth it on GPUs for many images; the first
    image then pays the compile time). `name` is its column in the evaluation tables, `source` the
    weights file it came from (reported next to the tables). `base` is what the generators correct:
    "noisy", or "oidn" / "oidn-fast" for refiners (then OIDN runs first, at that base's qualities, inside
    the call). `normalize_exposure` scales dim images up for the networks (exposure.py); False is the
    measurement without it.
    `dark_pass` denoises the image a second time at DARK_GAIN times the exposure where it has dark
    regions, and takes those from it (exposure.dark_weights): up to twice the network time.
    `ensemble` (1, 2, 4 or 8) averages the networks' outputs over that many symmetries of the input
    (symmetry.py), at that many times the network time. `keep_resolved` moves the output back toward the
    input where the input is nearly converged and the output departs from it beyond its noise
    (resolved.py); it needs the variance layers (diffuse_var, specular_var) and is skipped without them.
    `engine` runs the generators' forward passes: "torch" (the reference), or on a CPU their exported
    ONNX graphs in "onnxruntime" (float32) or "openvino" (`dtype` as for torch: its
    INFERENCE_PRECISION_HINT); "auto" is openvino on a CPU and torch on a GPU (engines.resolve_engine).
    Everything around the networks is the same in every engine.
    Implements pipeline.evaluation.baselines.Denoiser (name, device, denoise, synchronize).
    """

    def __init__(self, diffuse: nn.Module, specular: nn.Module | None, *, device: str | torch.device = "cpu",
                 tile: int | None = None, overlap: int | None = None, dtype: torch.dtype | None = None,
                 compile: bool = False, name: str = "admc", source: str | None = None,
                 normalize_exposure: bool = True, dark_pass: bool = False, ensemble: int = 1,
                 engine: str = "torch", keep_resolved: bool = False, oidn_blend: dict[str, float] | None = None) -> None:
        if tile is not None and tile < 1:
            raise ValueError(f"FullImageDenoiser: tile must be >= 1, got {tile}")
        if ensemble not in ENSEMBLE_CODES:
            raise ValueError(f"FullImageDenoiser: ensemble must be one of {tuple(ENSEMBLE_CODES)}, got {ensemble!r}")
        self.torch_device = torch.device(device)
        if self.torch_device.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError(f"FullImageDenoiser: device {str(device)!r} asked for, but torch sees no CUDA GPU")
        engine = resolve_engine(engine, self.torch_device)
        self.dtype = dtype or default_precision(engine, self.torch_device)
        check_engine(engine, self.torch_device, self.dtype)
        if compile and engine != "torch":
            raise ValueError(f"FullImageDenoiser: compile is torch.compile, engine {engine!r} compiles its own graph")
        self.base = getattr(getattr(diffuse, "config", None), "base", "noisy")
        self.noise_branches = {branch for branch, g in (("diffuse", diffuse), ("specular", specular))
                               if getattr(getattr(g, "config", None), "noise_input", False)}
        """The branches whose generator reads its noise map (model.noise_input) as a last feature channel."""
        self.generators = {"diffuse": self._prepare(diffuse)}
        if specular is not None:
            self.generators["specular"] = self._prepare(specular)
        radius = max((receptive_radius(g) if isinstance(g, Generator) else 0) for g in self.generators.values())
        if overlap is None:
            if not all(isinstance(g, Generator) for g in self.generators.values()):
                raise ValueError("FullImageDenoiser: overlap must be given for modules that are not admc Generators")
            overlap = radius
        if overlap < radius:
            raise ValueError(f"FullImageDenoiser: overlap {overlap} is below the receptive field radius {radius} "
                             f"of the generator; tiles would not match the untiled image (visible seams)")
        self.alignment = max(getattr(g, "alignment", 1) for g in self.generators.values())
        if compile:
            self.generators = {branch: torch.compile(g) for branch, g in self.generators.items()}
        if engine != "torch":
            self.generators = onnx_generators(self.generators, engine, self.dtype)
        self.engine = engine
        self.memory_format = MEMORY_FORMAT if engine == "torch" else torch.contiguous_format
        """The inputs' layout: torch's convs want channels_last; the exported graphs take NCHW, so their
        tiles are then row copies, not transposes."""
        self.tile = tile or default_tile(self.torch_device, overlap, engine)
        self.overlap = overlap
        self.device = (_device_description(self.torch_device) + f", {engine} {precision_name(self.dtype)}"
                       + (f", ensemble of {ensemble}" if ensemble > 1 else "")
                       + (", dark pass" if dark_pass else "")
                       + (", keeps resolved input" if keep_resolved else ""))
        self.name, self.source = name, source
        self.normalize_exposure = normalize_exposure
        self.dark_pass = dark_pass
        self.ensemble = ensemble
        self.keep_resolved = keep_resolved
        self.oidn_blend = dict(oidn_blend or {})
        if self.oidn_blend and self.base != "noisy":
            raise ValueError("FullImageDenoiser: an OIDN blend is for admc's own output (base 'noisy'), not a refiner's")
        if self.oidn_blend:
            self.device += ", blended with OIDN"

    def _prepare(self, generator: nn.Module) -> nn.Module:
        return generator.to(self.torch_device, memory_format=MEMORY_FORMAT).eval()

    def synchronize(self) -> None:
        if self.torch_device.type == "cuda":
            torch.cuda.synchronize(self.torch_device)

    def denoise(self, layers: dict[str, np.ndarray]) -> np.ndarray:
        return self(layers).image

    def missing_layers(self, layers: dict[str, np.ndarray]) -> list[str]:
        """The variance layers these weights read (model.noise_input) that `layers` lacks, for the branches
        that would run on them."""
        branches = ["diffuse"] + (["specular"] if "specular" in layers and "specular" in self.generators else [])
        return [f"{b}_var" for b in branches if b in self.noise_branches and f"{b}_var" not in layers]

    def __call__(self, layers: dict[str, np.ndarray]) -> DenoiseResult:
        """`layers`: diffuse, [specular], albedo, normal, [depth], [coverage] as (H, W, C) float arrays, and
        diffuse_var [and specular_var] (the variance of each pixel's mean) for weights with model.noise_input."""
        start = time.perf_counter()
        with torch_inline() if self.engine != "torch" else contextlib.nullcontext():  # torch's pool spins
            return self._denoise(layers, start)

    def _denoise(self, layers: dict[str, np.ndarray], start: float) -> DenoiseResult:
        missing = self.missing_layers(layers)
        if missing:
            raise MissingVarianceError(
                f"denoiser input lacks layer(s) {', '.join(missing)}, which {self.source or 'these weights'} read "
                "(model.noise_input: the variance of each pixel's mean, as `admc-pipe render` writes)")
        run_specular = "specular" in layers and "specular" in self.generators
        reads = tuple(f"{b}_var" for b in ("diffuse", "specular")[:1 + run_specular]
                      if b in self.noise_branches or (self.keep_resolved and f"{b}_var" in layers))
        clean, sanitized = sanitize_layers(layers, reads)
        run_specular = "specular" in clean and "specular" in self.generators
        gain = exposure_gain(_beauty(clean["diffuse"], clean.get("specular"))) if self.normalize_exposure else 1.0
        feats = self._tensor(features(clean["normal"], clean["depth"], clean["albedo"], clean["coverage"]))
        passes = [self._pass(clean, feats, gain, run_specular)]
        diffuse, specular = passes[0].diffuse, passes[0].specular
        dark_share = 0.0
        if self.dark_pass:
            weights = dark_weights(_beauty(diffuse, specular), gain, clean["coverage"])
            if weights.any():
                region = dark_region(weights, self.overlap, self.alignment)
                passes.append(self._pass(clean, feats, gain * DARK_GAIN, run_specular, region))
                share = weights[region]
                diffuse[region] += share * (passes[1].diffuse - diffuse[region])
                if run_specular:
                    specular[region] += share * (passes[1].specular - specular[region])
                dark_share = float(weights.mean())
        base_seconds = sum(p.base_seconds for p in passes)
        if self.oidn_blend:
            blend_start = time.perf_counter()
            diffuse, specular = _blend_with_oidn(clean, diffuse, specular, run_specular, self.oidn_blend)
            base_seconds += time.perf_counter() - blend_start
        resolved_share = 0.0
        if self.keep_resolved:
            diffuse, specular, resolved_share = _keep_resolved(clean, diffuse, specular, run_specular)
        return DenoiseResult(
            image=_beauty(diffuse, specular), diffuse=diffuse, specular=specular,
            branches=("diffuse", "specular")[:1 + run_specular],
            specular_passed_through="specular" in clean and not run_specular, sanitized=sanitized,
            nonfinite_outputs=sum(p.nonfinite for p in passes), tiles=passes[0].tiles,
            network_seconds=sum(p.network_seconds for p in passes), base_seconds=base_seconds,
            exposure_gain=gain, dark_share=dark_share, resolved_share=resolved_share,
            seconds=time.perf_counter() - start,
        )

    def _pass(self, clean: dict[str, np.ndarray], feats: Tensor, gain: float, run_specular: bool,
              region: tuple[slice, slice] = WHOLE_IMAGE) -> _Pass:
        """The networks on the radiance times `gain`, their output divided by it: linear, in the input's units.

        Only the image's `region` (rows, columns) comes out. The networks see that crop of the inputs, so
        wherever the crop keeps a receptive-field halo (or reaches the image border) the output equals
        the whole image's, as between tiles (tiling.py); a refiner's OIDN bases still come from the
        whole image, as in a whole pass."""
        exposed = {name: clean[name] * np.float32(gain) for name in ("diffuse", "specular") if name in clean}
        base_start = time.perf_counter()
        bases = self._bases({**clean, **exposed}, ("diffuse", "specular")[:1 + run_specular], region)
        base_seconds = time.perf_counter() - base_start
        albedo = clean["albedo"][region]
        inputs = {"diffuse": diffuse_forward(exposed["diffuse"][region], albedo)}
        if run_specular:
            inputs["specular"] = specular_forward(exposed["specular"][region])
        feats = feats[(..., *region)]
        branch_feats = {branch: self._with_noise(branch, feats, clean, exposed, gain, region) for branch in inputs}

        self.synchronize()
        net_start = time.perf_counter()
        jobs = {}
        for branch, log_input in inputs.items():
            generator = self.generators[branch]
            if isinstance(generator, OnnxGenerator) and region != WHOLE_IMAGE:
                generator = generator.one_off  # a crop of its own size: no compile for it
            jobs[branch] = (generator, self._tensor(log_input), branch_feats[branch], bases.get(branch))
        outputs, nonfinite = {}, 0
        with torch.inference_mode():  # the network's outputs are inference tensors: clamped in place
            for branch, out in self._run(jobs).items():
                if not torch.isfinite(out.sum()):  # a NaN or an infinity reaches the sum: count and zero them
                    nonfinite += int((~torch.isfinite(out)).sum())
                    out = torch.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
                outputs[branch] = out.clamp_(0.0, LOG_MAX[branch])
        outputs = {b: o[0].permute(1, 2, 0).cpu().numpy() for b, o in outputs.items()}  # cpu() synchronises
        network_seconds = time.perf_counter() - net_start
        outputs = _keep_environment(outputs, inputs, clean["coverage"][region])

        diffuse = diffuse_inverse(outputs["diffuse"], albedo) / np.float32(gain)
        if run_specular:
            specular = specular_inverse(outputs["specular"]) / np.float32(gain)
        else:
            specular = clean["specular"][region] if "specular" in clean else None  # passed through, never written
        _, _, height, width = jobs["diffuse"][1].shape
        tiles = math.ceil(height / self.tile) * math.ceil(width / self.tile)
        return _Pass(diffuse, specular, nonfinite, tiles, network_seconds, base_seconds)

    def _with_noise(self, branch: str, feats: Tensor, clean: dict[str, np.ndarray], exposed: dict[str, np.ndarray],
                    gain: float, region: tuple[slice, slice]) -> Tensor:
        """The features a branch's generator reads: + its noise map for model.noise_input, from the exposed
        radiance (a variance scales with the square of the exposure), over `region`."""
        if branch not in self.noise_branches:
            return feats
        variance = clean[f"{branch}_var"][region] * np.float32(gain) ** 2
        noise = (diffuse_noise(variance, exposed["diffuse"][region], clean["albedo"][region]) if branch == "diffuse"
                 else specular_noise(variance, exposed["specular"][region]))
        return torch.cat([feats, self._tensor(noise)], dim=1).contiguous(memory_format=self.memory_format)

    def _tensor(self, hwc: np.ndarray) -> Tensor:
        t = torch.from_numpy(np.ascontiguousarray(hwc)).permute(2, 0, 1).unsqueeze(0).to(self.torch_device)
        return t.contiguous(memory_format=self.memory_format)

    def _bases(self, clean: dict[str, np.ndarray], branches: tuple[str, ...],
               region: tuple[slice, slice]) -> dict[str, Tensor]:
        """A refiner's inputs from OIDN on the whole image, cropped to `region`, per branch it runs, in that
        branch's log domain; {} for base "noisy"."""
        if self.base == "noisy":
            return {}
        linear = oidn_bases({name: clean[name] for name in ("albedo", "normal", *branches)}, self.base)
        forward = {"diffuse": lambda x: diffuse_forward(x, clean["albedo"][region]), "specular": specular_forward}
        return {branch: self._tensor(forward[branch](linear[branch][region])) for branch in branches}

    def _run(self, jobs: dict[str, tuple[nn.Module, Tensor, Tensor, Tensor | None]]) -> dict[str, Tensor]:
        """Each branch's `(generator, noisy, feats, base)` through its generator: tiled, averaged over the
        ensemble's symmetries. Per symmetry, both branches' tiles go to engines.run_together in one list, so
        that an exported graph's tiles, and the two branches, can run at once."""
        codes = ENSEMBLE_CODES[self.ensemble]
        summed = {}
        for code in codes:
            plans, calls = [], []  # plans: (branch, its tiles' windows, its turned input) in the calls' order
            for branch, (generator, noisy, feats, base) in jobs.items():
                turned = apply(noisy, code)
                windows, tiles = tile_calls(turned, apply(feats, code, normals=True), self.tile, self.overlap,
                                            self.alignment, None if base is None else apply(base, code))
                plans.append((branch, windows, turned))
                calls += [(generator, tile) for tile in tiles]
            outputs = run_together(calls)
            with torch.inference_mode(), autocast_for(self.torch_device, self.dtype):  # calls run as read
                for branch, windows, turned in plans:  # paste's output is new: the sum can grow in place
                    one = undo(paste(windows, itertools.islice(outputs, len(windows)), turned), code).float()
                    summed[branch] = summed[branch].add_(one) if branch in summed else one
        if len(codes) > 1:
            for out in summed.values():
                out /= len(codes)
        return summed


def dark_region(weights: np.ndarray, halo: int, alignment: int) -> tuple[slice, slice]:
    """The rows and columns the dark pass must run on: the bounding box of the pixels with a weight, grown
    by the networks' halo and started on their grid (tiling.axis_windows' two conditions for exactness).
    A small object's shadows on a black background need a fraction of the image."""
    def span(lit: np.ndarray) -> slice:
        first, last = np.flatnonzero(lit)[[0, -1]]
        start = max(int(first) - halo, 0)
        return slice(start - start % alignment, min(int(last) + 1 + halo, lit.size))

    dark = weights[..., 0] > 0
    return span(dark.any(axis=1)), span(dark.any(axis=0))


def _keep_resolved(clean: dict[str, np.ndarray], diffuse: np.ndarray, specular: np.ndarray | None,
                   run_specular: bool) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Each denoised branch with a variance layer moved toward its input where that is resolved (resolved.py);
    returns the branches and the mean weight of the input over them."""
    value = _beauty(diffuse, specular)
    outputs = {"diffuse": diffuse, "specular": specular}
    shares = []
    for branch in ("diffuse", "specular")[:1 + run_specular]:
        if f"{branch}_var" in clean:
            outputs[branch], share = keep_resolved(outputs[branch], clean[branch], clean[f"{branch}_var"], value)
            shares.append(share)
    return outputs["diffuse"], outputs["specular"], float(np.mean(shares)) if shares else 0.0


def _blend_with_oidn(clean: dict[str, np.ndarray], diffuse: np.ndarray, specular: np.ndarray | None,
                     run_specular: bool, shares: dict[str, float]) -> tuple[np.ndarray, np.ndarray | None]:
    """Each branch's output blended with OIDN's per-branch output (high, as a refiner's base: oidn_base.py):
    share * output + (1 - share) * OIDN, the share a fine-tune chose on its val patches (train.oidn_blend)."""
    branches = ("diffuse", "specular")[:1 + run_specular]
    oidn = oidn_bases({name: clean[name] for name in ("albedo", "normal", *branches)}, "oidn")
    out = {"diffuse": diffuse, "specular": specular}
    for branch in branches:
        share = np.float32(shares.get(branch, 1.0))
        if share < 1:
            out[branch] = share * out[branch] + (1 - share) * oidn[branch]
    return out["diffuse"], out["specular"]


def _beauty(diffuse: np.ndarray, specular: np.ndarray | None) -> np.ndarray:
    """The final image of the two branches (a new array, never one of them)."""
    return diffuse + specular if specular is not None else diffuse.copy()


@dataclass
class _Pass:
    """One run of the networks at one exposure: linear outputs in the input's units, and its costs."""

    diffuse: np.ndarray
    specular: np.ndarray | None
    nonfinite: int
    tiles: int
    network_seconds: float
    base_seconds: float


def _keep_environment(outputs: dict[str, np.ndarray], inputs: dict[str, np.ndarray],
                      coverage: np.ndarray) -> dict[str, np.ndarray]:
    """Log-domain outputs with the input kept wherever coverage is 0.

    Every camera sample of such a pixel escaped to the environment without meeting a surface: it shows
    the environment directly, with no light transport sampled and so no Monte Carlo noise to remove,
    and its features (no normal, depth 1, albedo 1) tell the network nothing. The network's output
    there was a guess (around a small object on a black background: a glow); the input is the answer,
    and it hides no light. A refiner keeps it too: OIDN's output there is worse than exact (a halo around
    small emitters on a black void: up to 1000x the studio scenes' relMSE).
    Partly covered pixels (silhouettes) and the environment seen in mirrors or through smooth glass
    (which the integrator gives a coverage: it is noisy) are denoised as usual.
    """
    environment = coverage == 0
    if not environment.any():  # most images: no copy
        return outputs
    return {branch: np.where(environment, inputs[branch], out) for branch, out in outputs.items()}


def sanitize_layers(layers: dict[str, np.ndarray], variances: tuple[str, ...] = ()
                    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, int]]]:
    """Check shapes, fill a missing depth/coverage (MISSING_LAYERS) and sanitize every layer, and the
    `variances` (names of buffers.VARIANCE_LAYERS: those weights with model.noise_input read; others are ignored).

    Returns the clean float32 layers and, per layer with any repair, the nonzero counts of NaN,
    +-Inf and out-of-range values (negative radiance or albedo, radiance above RADIANCE_MAX, ...).
    """
    missing = [name for name in REQUIRED_LAYERS if name not in layers]
    if missing:
        raise KeyError(f"denoiser input lacks layer(s) {', '.join(missing)} (has {', '.join(sorted(layers))})")
    size = np.shape(layers["diffuse"])[:2]
    for name in (*DENOISER_LAYERS, *variances):
        expected = (*size, len(LAYERS[name].channels))
        if name in layers and np.shape(layers[name]) != expected:
            raise ValueError(f"denoiser input layer {name!r} has shape {np.shape(layers[name])}, "
                             f"expected {expected} to match diffuse")
    if size[0] < 1 or size[1] < 1:
        raise ValueError(f"denoiser input is empty ({size[0]}x{size[1]})")
    filled = dict(layers)
    for name, value in MISSING_LAYERS.items():
        filled.setdefault(name, np.full((*size, 1), value, dtype=np.float32))
    clean, report = {}, {}
    for name in (*DENOISER_LAYERS, *variances):
        if name in filled:
            clean[name], counts = sanitize(filled[name], name)
            nonzero = {kind: n for kind, n in counts.items() if n}
            if nonzero:
                report[name] = nonzero
    return clean, report


COLUMN_NAMES = {"noisy": "admc", "oidn": "admc+oidn", "oidn-fast": "admc+oidn"}
"""A learned denoiser's default column name in the tables, by the base its weights record."""


def load_denoiser(path, *, device: str | torch.device = "cpu", tile: int | None = None,
                  compile: bool = False, name: str | None = None, normalize_exposure: bool = True,
                  dark_pass: bool = False, ensemble: int = 1, engine: str = "torch",
                  dtype: torch.dtype | None = None, keep_resolved: bool = False,
                  oidn_blend: bool = True) -> FullImageDenoiser:
    """Both branches' generators from a training checkpoint or exported weights, ready to denoise;
    named `name`, else after the base the file records (COLUMN_NAMES).

    Refuses weights trained on other transforms than this code applies (their outputs would be
    inverted wrongly); a file without a specular branch denoises diffuse only. Weights that ship an OIDN
    blend (train.oidn_blend) are blended with OIDN's output unless `oidn_blend` is False.
    """
    from admc.stores.checkpoints import CheckpointError, load_network, read_blend, read_networks

    from ..nets.settings import ModelSettings
    from ..transforms import transform_spec

    nets, model, transform = read_networks(path)
    if transform != transform_spec():
        changed = differing_keys(transform, transform_spec())
        raise CheckpointError(f"{path}: trained with other data transforms than this code applies ({', '.join(changed)})")
    if "diffuse" not in nets:
        raise CheckpointError(f"{path}: has no diffuse branch")
    try:
        config = ModelSettings.from_saved(model)
        config.check()
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: its model metadata {model} is not an architecture this code builds "
                              f"({exc})") from None
    generators = {}
    for branch, state in nets.items():
        generator = build_generator(config)
        load_network(generator, state["generator"], f"{path}: {branch} generator",
                     "the architecture its own metadata describes")
        generators[branch] = generator.eval()
    return FullImageDenoiser(generators["diffuse"], generators.get("specular"), device=device, tile=tile,
                             compile=compile, name=name or COLUMN_NAMES[config.base], source=str(path),
                             normalize_exposure=normalize_exposure, dark_pass=dark_pass, ensemble=ensemble,
                             engine=engine, dtype=dtype, keep_resolved=keep_resolved,
                             oidn_blend=read_blend(path) if oidn_blend else None)
