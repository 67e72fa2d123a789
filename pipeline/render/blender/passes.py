"""Blender's passes to admc's buffers: the sub-renders of one (scene, spp) combined into one render.

Per sub-render (Cycles' own passes, Blender 5 names): diffuse = (Diffuse Direct + Diffuse Indirect) x
Diffuse Color; specular = Combined - diffuse (glossy, transmission, emission and the environment);
albedo = Denoising Albedo, clipped to 1 (Cycles gives a lamp seen directly its emission there; admc's
renders give emitters albedo 1); normal = Denoising Normal, which Cycles writes in its camera space (x right, y
up, z forward) and admc's frame turns z around; depth = Denoising Depth (0 where the camera ray hit
nothing); coverage 0 where the environment is seen directly (`coverage`), averaged over the
sub-renders. Cycles gives no per-pixel variance, so the render is made of
several independent sub-renders (seeds of their own) and each branch's variance of the pixel mean comes
from their spread: with K sub-renders of s_k samples (S in all) and means m_k, the per-sample variance is
sum s_k (m_k - m)^2 / (K - 1), and the variance of the mean that divided by S.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from admc.common.camera import to_admc_camera
from admc.stores.exr_parts import read_channels

LIGHT = {"direct": "Diffuse Direct", "indirect": "Diffuse Indirect", "colour": "Diffuse Color"}
FEATURES = {"albedo": "Denoising Albedo", "normal": "Denoising Normal", "depth": "Denoising Depth"}


class PassError(ValueError):
    """A sub-render lacks a pass admc needs (the worker switches them all on: a Blender that did not)."""


def read_subrender(path: Path, view_layer: str) -> tuple[dict[str, np.ndarray], float]:
    """One sub-render's buffers in admc's terms, and Cycles' path-tracing seconds from its header."""
    header, planes = read_channels(path)
    prefix = f"{view_layer}."

    def rgb(name: str, channels: str = "RGB") -> np.ndarray:
        try:
            return np.stack([planes[f"{prefix}{name}.{c}"] for c in channels], axis=-1)
        except KeyError:
            raise PassError(f"{path}: no pass {name!r} in view layer {view_layer!r}") from None

    combined = rgb("Combined")
    diffuse = (rgb(LIGHT["direct"]) + rgb(LIGHT["indirect"])) * rgb(LIGHT["colour"])
    depth = rgb(FEATURES["depth"], "Z")
    buffers = {
        "diffuse": diffuse,
        "specular": np.maximum(combined - diffuse, 0.0),
        "albedo": np.clip(rgb(FEATURES["albedo"]), 0.0, 1.0),
        "normal": to_admc_camera(rgb(FEATURES["normal"], "XYZ"), "cycles"),
        "depth": depth,
        "coverage": coverage(depth, combined, rgb("Environment")),
    }
    return buffers, _seconds(header.get(f"cycles.{view_layer}.render_time", "0"))


def coverage(depth: np.ndarray, combined: np.ndarray, environment: np.ndarray) -> np.ndarray:
    """(H, W, 1): 0 where the pixel sees the environment directly (no surface depth, and Combined is the
    Environment pass), 1 elsewhere. Cycles' denoising data follow near-specular bounces, as admc's renders
    follow delta ones: a mirror or clear glass that shows the sky has no denoising depth, yet its pixel is
    as noisy as the surface is curved, so it keeps coverage 1 and is denoised (admc passes coverage-0
    pixels through unchanged)."""
    direct = np.abs(combined - environment).sum(-1, keepdims=True) <= 1e-3 * np.abs(combined).sum(-1, keepdims=True)
    return ((depth > 0) | ~direct).astype(np.float32)


def _seconds(text: str) -> float:
    """Blender's "MM:SS.cc" (or "HH:MM:SS.cc") as seconds."""
    total = 0.0
    for part in str(text).split(":"):
        total = total * 60 + float(part)
    return total


def combine(subrenders: list[tuple[dict[str, np.ndarray], int]]) -> dict[str, np.ndarray]:
    """Sub-renders [(buffers, spp)] as one render: spp-weighted means, and each branch's variance of the
    pixel mean from the sub-renders' spread (0 with a single sub-render)."""
    weights = np.array([spp for _, spp in subrenders], np.float64)
    total = weights.sum()
    out = {}
    for name in subrenders[0][0]:
        stack = np.stack([buffers[name].astype(np.float64) for buffers, _ in subrenders])
        out[name] = np.tensordot(weights / total, stack, axes=1)
        if name in ("diffuse", "specular"):
            if len(subrenders) > 1:
                spread = np.tensordot(weights, np.square(stack - out[name]), axes=1) / (len(subrenders) - 1)
                out[f"{name}_var"] = spread / total
            else:
                out[f"{name}_var"] = np.zeros_like(out[name])
    return {name: np.ascontiguousarray(array, dtype=np.float32) for name, array in out.items()}
