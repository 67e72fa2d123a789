"""Each branch's generator as an ONNX graph, and a JSON of what runs around it: admc without Python.

A graph is one branch's `Generator.forward`, darkness gate and input skip included, with dynamic
height and width: inputs `noisy` (1, 3, H, W) in the branch's log domain, `features` (1, 7, H, W), for
weights with model.noise_input `noise` (1, 1, H, W: the branch's noise map, transforms.noise_forward) and, for
a refiner, `base` (1, 3, H, W: OIDN's output of the branch, same log domain); output `denoised`
(1, 3, H, W), log domain. Everything else (sanitising, the forward and inverse transforms, the output
clamp, environment pixels, tiling) is described in the JSON (`export_manifest`) so that a renderer can
do it in its own code; docs/engines.md spells it out.
"""

from __future__ import annotations

import copy
import io
import warnings
from pathlib import Path

import torch
from torch import nn

from admc.common.buffers import LAYERS, VARIANCE_LAYERS
from admc.common.layout import BASE_QUALITIES, FEATURE_CHANNELS
from admc.common.metrics import RELMSE_EPS

from ..nets.generator import Generator
from ..transforms import NOISE_STD_UNIT
from . import exposure, resolved

OPSET = 17
"""ONNX opset of the graphs: ONNX Runtime and OpenVINO of 2026 both run it (STACK_NOTES.md)."""
MANIFEST_NAME = "admc.json"
FORMAT = "admc-onnx"
FORMAT_VERSION = 4
"""2 added `missing`, `variance`, `exposure` and `keep_resolved`: what `admc-pipe denoise` does around the graphs;
3 added `oidn_blend` (present where the weights ship one: train.oidn_blend), with `weights` where the blend's OIDN
runs weights fine-tuned with the model (train.oidn_minutes); 4 added its `prefiltered_guides` (the branches whose
fine-tuned OIDN is its large network on prefiltered guides: train.oidn_network = "large")."""


INPUT_CHANNELS = {"noisy": 3, "features": len(FEATURE_CHANNELS), "noise": 1, "base": 3}


def input_names(generator: Generator) -> list[str]:
    """The graph's inputs, in the order its forward takes them: noisy, features, [noise], [base]."""
    return (
        ["noisy", "features"]
        + (["noise"] if generator.config.noise_input else [])
        + (["base"] if generator.config.refines else [])
    )


class _NoiseAsInput(nn.Module):
    """A model.noise_input generator with its noise map as an input of its own (the generator reads it as
    the features' last channel): a renderer passes the 7 features as for any weights, and the map beside them."""

    def __init__(self, generator: Generator) -> None:
        super().__init__()
        self.generator = generator

    def forward(
        self, noisy: torch.Tensor, features: torch.Tensor, noise: torch.Tensor, base: torch.Tensor | None = None
    ) -> torch.Tensor:
        return self.generator(noisy, torch.cat([features, noise], dim=1), base)


def export_generator(generator: Generator, path: Path) -> None:
    """Write `generator` as an ONNX graph (generator_graph) at `path`."""
    Path(path).write_bytes(generator_graph(generator))


def generator_graph(generator: Generator) -> bytes:
    """`generator` (float32, on the CPU; the module itself is left as it is) as a serialised ONNX graph.

    The trace runs on a small example with height and width marked dynamic; the darkness gate traces
    as max pooling (generator.light_within), which is the same dilation for any size."""
    module = copy.deepcopy(generator).float().cpu().eval()
    names = input_names(module)
    size = 2 * module.alignment * 4
    example = tuple(torch.rand(1, INPUT_CHANNELS[name], size, size) for name in names)
    if module.config.noise_input:
        module = _NoiseAsInput(module)
    dynamic = {name: {2: "height", 3: "width"} for name in [*names, "denoised"]}
    graph = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tracer's warnings about shape checks turned into constants
        torch.onnx.export(
            module,
            example,
            graph,
            input_names=names,
            output_names=["denoised"],
            dynamic_axes=dynamic,
            opset_version=OPSET,
            dynamo=False,
        )
    return graph.getvalue()


def export_manifest(
    generators: dict[str, nn.Module],
    transform: dict,
    log_max: dict[str, float],
    missing: dict[str, float],
    oidn_blend: dict[str, float] | None = None,
    oidn_weights: dict[str, str] | None = None,
    prefiltered_guides: tuple[str, ...] = (),
) -> dict:
    """What a renderer must run around the graphs, JSON-ready (see docs/engines.md); `missing` is the constant
    a layer the input lacks is filled with (depth, coverage). examples/onnx_denoise.py follows it and
    nothing else, and tests/test_export_consumer.py checks that it gives what `admc-pipe denoise` gives."""
    first = next(iter(generators.values()))
    halo = max(g.receptive_radius() for g in generators.values())
    variance = LAYERS[VARIANCE_LAYERS[0]]  # the variance layers share one rule
    return {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "opset": OPSET,
        "base": first.config.base,
        **({"base_quality": BASE_QUALITIES[first.config.base]} if first.config.refines else {}),
        **({"noise_input": True} if first.config.noise_input else {}),  # absent without: the JSON as before
        "graphs": {branch: f"{branch}.onnx" for branch in generators},
        "inputs": {
            "noisy": "the branch's radiance in its log domain (transform.diffuse or transform.specular), RGB",
            "features": list(FEATURE_CHANNELS),
            **(
                {
                    "noise": "the branch's noise map (1 channel) from the render's variance of each pixel's mean: "
                    "log1p(std / noise_std_unit) / log1p(1 / noise_std_unit), std = mean over RGB of "
                    "sqrt(variance) / (radiance + scale), scale = albedo + eps for diffuse, 1 for specular "
                    "(radiance and variance at the exposure the network sees)"
                }
                if first.config.noise_input
                else {}
            ),
            **(
                {
                    "base": "OIDN's output of the branch (hdr; diffuse with albedo + normal, specular alone) at "
                    "base_quality, same log domain, RGB"
                }
                if first.config.refines
                else {}
            ),
        },
        "layout": "NCHW float32, N = 1",
        "output": {
            "denoised": "the branch in its log domain: clamp to [0, log_max], invert with transform.*_inverse",
            "log_max": log_max,
            "environment": "where coverage = 0 keep the input (noisy) value instead of the output",
        },
        "missing": {**missing, "rule": "a layer the input lacks is this constant at every pixel"},
        "variance": {
            "layers": dict(zip(("diffuse", "specular"), VARIANCE_LAYERS)),
            "what": "the render's variance of each pixel's mean, per branch, RGB (optional: keep_resolved uses it)",
            "sanitize": {"min": variance.low, "max": variance.high, "nan": variance.nan},
        },
        "exposure": {
            "trained_brightness": exposure.TRAINED_BRIGHTNESS,
            "luminance": [float(w) for w in exposure.LUMINANCE],
            "lit": exposure.LIT,
            "rule": "gain k = 2^n multiplies the sanitised diffuse and specular (and, for the noise map, the "
            "variances by k^2) before everything else, OIDN's bases included, and divides both denoised "
            "branches after the inverse. "
            "level = exp(mean(log(L))) over the pixels of diffuse + specular whose luminance L = "
            "luminance . RGB exceeds lit; k = 1 if there are none or level >= trained_brightness, else "
            "n = max(0, min(round(log2(trained_brightness / level)), floor(log2(radiance_max / peak)))), "
            "peak = the largest value of diffuse + specular (if > 0)",
        },
        **(
            {
                "oidn_blend": {
                    "shares": dict(oidn_blend),
                    "quality": BASE_QUALITIES["oidn"],
                    "rule": "after the inverse (and / k), before keep_resolved, per branch with a share: "
                    "out = share out + "
                    "(1 - share) OIDN(clean branch) at that branch's quality, diffuse with the sanitised albedo and "
                    "normal as guides, specular alone, both at the input's own exposure (hdr), negatives and "
                    "non-finite values set to 0",
                    **(
                        {
                            "weights": dict(oidn_weights),
                            "weights_rule": "OIDN runs each branch with the weights in that file (TZA, its own "
                            "format: the filter's 'weights' data) at quality high, instead of its built-in ones",
                            "prefiltered_guides": list(prefiltered_guides),
                            "prefiltered_guides_rule": "for these branches OIDN first denoises the albedo and the "
                            "normal guide on their own (a filter with only that image as input and output, quality "
                            "high), then runs the branch's weights on those guides with cleanAux = true",
                        }
                        if oidn_weights
                        else {}
                    ),
                }
            }
            if oidn_blend
            else {}
        ),
        "keep_resolved": {
            "radius": resolved.RADIUS,
            "margin": resolved.MARGIN,
            "converged": resolved.CONVERGED,
            "unsampled": resolved.UNSAMPLED,
            "relmse_eps": RELMSE_EPS,
            "rule": "last, per branch with a variance layer, on the outputs after the inverse (and / k): "
            "m(x) = (x.R + x.G + x.B) / 3; box(x) = mean over the (2 radius + 1)^2 window, the image "
            "mirrored at its edges (d c b a | a b c d); s = m(diffuse + specular)^2 + relmse_eps, both "
            "branches as denoised before this step; v = max(box(m(variance) / s), 0); resolved = v < "
            "converged and box(variance is 0 in all of R, G, B) <= unsampled; b = box(m((out - noisy)^2) "
            "/ s) - v (1 + margin sqrt(2) / (2 radius + 1)); w = clip(b / max(b + v, 1e-30), 0, 1) where "
            "resolved and b > 0, else 0; out += w (noisy - out); noisy and variance are the sanitised "
            "input's, at its own exposure",
        },
        "eps": transform["eps"],
        **({"noise_std_unit": NOISE_STD_UNIT} if first.config.noise_input else {}),
        "transform": transform,
        "gate_radius": {branch: g.gate_radius for branch, g in generators.items()},
        "receptive_radius": halo,
        "tile": {
            "halo": halo,
            "alignment": max(g.alignment for g in generators.values()),
            "rule": "crop each tile with `halo` pixels of image on every side that is not the image border "
            "(shift crops inwards at the borders, start them at multiples of `alignment`) and keep "
            "only its core: equal to the untiled result",
        },
    }
