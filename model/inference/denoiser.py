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
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor, nn

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
from .fine_tuned_oidn import partner_archives, partner_bases
from .exposure import DARK_GAIN, dark_region, dark_weights, exposure_gain
from .input_layers import sanitize_layers
from .oidn_base import oidn_bases
from .options import DenoiserOptions
from .resolved import keep_resolved
from .result import DenoiseResult
from .tiling import default_tile, paste, receptive_radius, tile_calls

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


def _device_description(device: torch.device) -> str:
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return f"{device.type} ({torch.get_num_threads()} threads)"


class FullImageDenoiser:
    """Sanitize -> forward transforms -> diffuse [and specular] generator -> inverse -> linear HDR.

    `diffuse` and `specular` are admc Generators (or any module called as `(noisy, features)`; those
    need an explicit `options.overlap`). They are moved to the device and put in eval mode. `options` says
    how it runs and what it does around the networks (options.py). A refiner's generators (config.base
    "oidn" / "oidn-fast") correct OIDN's output, which runs first, at that base's qualities, inside the call.
    Implements pipeline.evaluation.baselines.Denoiser (name, device, denoise, synchronize).
    """

    def __init__(
        self, diffuse: nn.Module, specular: nn.Module | None, options: DenoiserOptions = DenoiserOptions()
    ) -> None:
        self.options = options
        self.torch_device = torch.device(options.device)
        if self.torch_device.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError(
                f"FullImageDenoiser: device {str(options.device)!r} asked for, but torch sees no CUDA GPU"
            )
        engine = resolve_engine(options.engine, self.torch_device)
        self.dtype = options.dtype or default_precision(engine, self.torch_device)
        check_engine(engine, self.torch_device, self.dtype)
        if options.compile and engine != "torch":
            raise ValueError(f"FullImageDenoiser: compile is torch.compile, engine {engine!r} compiles its own graph")
        self.base = getattr(getattr(diffuse, "config", None), "base", "noisy")
        self.noise_branches = {
            branch
            for branch, g in (("diffuse", diffuse), ("specular", specular))
            if getattr(getattr(g, "config", None), "noise_input", False)
        }
        """The branches whose generator reads its noise map (model.noise_input) as a last feature channel."""
        self.generators = {"diffuse": self._prepare(diffuse)}
        if specular is not None:
            self.generators["specular"] = self._prepare(specular)
        radius = max((receptive_radius(g) if isinstance(g, Generator) else 0) for g in self.generators.values())
        overlap = options.overlap
        if overlap is None:
            if not all(isinstance(g, Generator) for g in self.generators.values()):
                raise ValueError("FullImageDenoiser: overlap must be given for modules that are not admc Generators")
            overlap = radius
        if overlap < radius:
            raise ValueError(
                f"FullImageDenoiser: overlap {overlap} is below the receptive field radius {radius} "
                f"of the generator; tiles would not match the untiled image (visible seams)"
            )
        self.alignment = max(getattr(g, "alignment", 1) for g in self.generators.values())
        if options.compile:
            self.generators = {branch: torch.compile(g) for branch, g in self.generators.items()}
        if engine != "torch":
            self.generators = onnx_generators(self.generators, engine, self.dtype)
        self.engine = engine
        self.memory_format = MEMORY_FORMAT if engine == "torch" else torch.contiguous_format
        """The inputs' layout: torch's convs want channels_last; the exported graphs take NCHW, so their
        tiles are then row copies, not transposes."""
        self.tile = options.tile or default_tile(self.torch_device, overlap, engine)
        self.overlap = overlap
        self.device = (
            _device_description(self.torch_device)
            + f", {engine} {precision_name(self.dtype)}"
            + (f", ensemble of {options.ensemble}" if options.ensemble > 1 else "")
            + (", dark pass" if options.dark_pass else "")
            + (", keeps resolved input" if options.keep_resolved else "")
        )
        self.name, self.source = options.name or "admc", options.source
        self.normalize_exposure = options.normalize_exposure
        self.dark_pass = options.dark_pass
        self.ensemble = options.ensemble
        self.keep_resolved = options.keep_resolved
        self.oidn_blend = dict(options.oidn_blend or {})
        if self.oidn_blend and self.base != "noisy":
            raise ValueError(
                "FullImageDenoiser: an OIDN blend is for admc's own output (base 'noisy'), not a refiner's"
            )
        self.oidn_partner = (
            partner_archives(options.oidn_partner, options.source or "weights")
            if self.oidn_blend and options.oidn_partner
            else None
        )
        if self.oidn_blend:
            self.device += ", blended with " + ("OIDN fine-tuned with it" if self.oidn_partner else "OIDN")

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
                "(model.noise_input: the variance of each pixel's mean, as `admc-pipe render` writes)"
            )
        run_specular = "specular" in layers and "specular" in self.generators
        reads = tuple(
            f"{b}_var"
            for b in ("diffuse", "specular")[: 1 + run_specular]
            if b in self.noise_branches or (self.keep_resolved and f"{b}_var" in layers)
        )
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
            partner = (self.oidn_partner, self.ensemble) if self.oidn_partner else None
            diffuse, specular = _blend_with_oidn(clean, diffuse, specular, run_specular, self.oidn_blend, partner)
            base_seconds += time.perf_counter() - blend_start
        resolved_share = 0.0
        if self.keep_resolved:
            diffuse, specular, resolved_share = _keep_resolved(clean, diffuse, specular, run_specular)
        return DenoiseResult(
            image=_beauty(diffuse, specular),
            diffuse=diffuse,
            specular=specular,
            branches=("diffuse", "specular")[: 1 + run_specular],
            specular_passed_through="specular" in clean and not run_specular,
            sanitized=sanitized,
            nonfinite_outputs=sum(p.nonfinite for p in passes),
            tiles=passes[0].tiles,
            network_seconds=sum(p.network_seconds for p in passes),
            base_seconds=base_seconds,
            exposure_gain=gain,
            dark_share=dark_share,
            resolved_share=resolved_share,
            seconds=time.perf_counter() - start,
        )

    def _pass(
        self,
        clean: dict[str, np.ndarray],
        feats: Tensor,
        gain: float,
        run_specular: bool,
        region: tuple[slice, slice] = WHOLE_IMAGE,
    ) -> _Pass:
        """The networks on the radiance times `gain`, their output divided by it: linear, in the input's units.

        Only the image's `region` (rows, columns) comes out. The networks see that crop of the inputs, so
        wherever the crop keeps a receptive-field halo (or reaches the image border) the output equals
        the whole image's, as between tiles (tiling.py); a refiner's OIDN bases still come from the
        whole image, as in a whole pass."""
        exposed = {name: clean[name] * np.float32(gain) for name in ("diffuse", "specular") if name in clean}
        base_start = time.perf_counter()
        bases = self._bases({**clean, **exposed}, ("diffuse", "specular")[: 1 + run_specular], region)
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

    def _with_noise(
        self,
        branch: str,
        feats: Tensor,
        clean: dict[str, np.ndarray],
        exposed: dict[str, np.ndarray],
        gain: float,
        region: tuple[slice, slice],
    ) -> Tensor:
        """The features a branch's generator reads: + its noise map for model.noise_input, from the exposed
        radiance (a variance scales with the square of the exposure), over `region`."""
        if branch not in self.noise_branches:
            return feats
        variance = clean[f"{branch}_var"][region] * np.float32(gain) ** 2
        noise = (
            diffuse_noise(variance, exposed["diffuse"][region], clean["albedo"][region])
            if branch == "diffuse"
            else specular_noise(variance, exposed["specular"][region])
        )
        return torch.cat([feats, self._tensor(noise)], dim=1).contiguous(memory_format=self.memory_format)

    def _tensor(self, hwc: np.ndarray) -> Tensor:
        t = torch.from_numpy(np.ascontiguousarray(hwc)).permute(2, 0, 1).unsqueeze(0).to(self.torch_device)
        return t.contiguous(memory_format=self.memory_format)

    def _bases(
        self, clean: dict[str, np.ndarray], branches: tuple[str, ...], region: tuple[slice, slice]
    ) -> dict[str, Tensor]:
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
                windows, tiles = tile_calls(
                    turned,
                    apply(feats, code, normals=True),
                    self.tile,
                    self.overlap,
                    self.alignment,
                    None if base is None else apply(base, code),
                )
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


def _keep_resolved(
    clean: dict[str, np.ndarray], diffuse: np.ndarray, specular: np.ndarray | None, run_specular: bool
) -> tuple[np.ndarray, np.ndarray | None, float]:
    """Each denoised branch with a variance layer moved toward its input where that is resolved (resolved.py);
    returns the branches and the mean weight of the input over them."""
    value = _beauty(diffuse, specular)
    outputs = {"diffuse": diffuse, "specular": specular}
    shares = []
    for branch in ("diffuse", "specular")[: 1 + run_specular]:
        if f"{branch}_var" in clean:
            outputs[branch], share = keep_resolved(outputs[branch], clean[branch], clean[f"{branch}_var"], value)
            shares.append(share)
    return outputs["diffuse"], outputs["specular"], float(np.mean(shares)) if shares else 0.0


def _blend_with_oidn(
    clean: dict[str, np.ndarray],
    diffuse: np.ndarray,
    specular: np.ndarray | None,
    run_specular: bool,
    shares: dict[str, float],
    partner: tuple[dict, int] | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Each branch's output blended with OIDN's per-branch output (high, as a refiner's base: oidn_base.py):
    share * output + (1 - share) * OIDN, the share a fine-tune chose on its val patches (train.oidn_blend).
    `partner` (TZA archives, ensemble): OIDN fine-tuned with the weights, run in place of its own networks."""
    branches = ("diffuse", "specular")[: 1 + run_specular]
    if partner:
        oidn = partner_bases(partner[0], clean, branches, partner[1])
    else:
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


def _keep_environment(
    outputs: dict[str, np.ndarray], inputs: dict[str, np.ndarray], coverage: np.ndarray
) -> dict[str, np.ndarray]:
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


COLUMN_NAMES = {"noisy": "admc", "oidn": "admc+oidn", "oidn-fast": "admc+oidn"}
"""A learned denoiser's default column name in the tables, by the base its weights record."""


def load_denoiser(path, options: DenoiserOptions = DenoiserOptions(), oidn_blend: bool = True) -> FullImageDenoiser:
    """Both branches' generators from a training checkpoint or exported weights, ready to denoise as
    `options` say; named `options.name`, else after the base the file records (COLUMN_NAMES); blended with
    OIDN at the shares the weights ship (train.oidn_blend) unless `oidn_blend` is False.

    Refuses weights trained on other transforms than this code applies (their outputs would be
    inverted wrongly); a file without a specular branch denoises diffuse only.
    """
    from admc.stores.checkpoints import CheckpointError, load_network, read_denoiser

    from ..nets.settings import ModelSettings
    from ..transforms import transform_spec

    (nets, model, transform), blend, partner = read_denoiser(path, oidn_blend)
    if transform != transform_spec():
        changed = differing_keys(transform, transform_spec())
        raise CheckpointError(
            f"{path}: trained with other data transforms than this code applies ({', '.join(changed)})"
        )
    if "diffuse" not in nets:
        raise CheckpointError(f"{path}: has no diffuse branch")
    try:
        config = ModelSettings.from_saved(model)
        config.check()
    except (TypeError, ValueError) as exc:
        raise CheckpointError(
            f"{path}: its model metadata {model} is not an architecture this code builds ({exc})"
        ) from None
    generators = {}
    for branch, state in nets.items():
        generator = build_generator(config)
        load_network(
            generator, state["generator"], f"{path}: {branch} generator", "the architecture its own metadata describes"
        )
        generators[branch] = generator.eval()
    return FullImageDenoiser(
        generators["diffuse"],
        generators.get("specular"),
        replace(
            options,
            name=options.name or COLUMN_NAMES[config.base],
            source=str(path),
            oidn_blend=blend,
            oidn_partner=partner or None,
        ),
    )
