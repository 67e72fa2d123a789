"""A denoiser's input layers checked, completed and sanitised: what every engine and pass reads."""

from __future__ import annotations

import numpy as np

from admc.common.buffers import DENOISER_LAYERS, LAYERS, MISSING_LAYERS, sanitize

REQUIRED_LAYERS = ("diffuse", "albedo", "normal")


def sanitize_layers(
    layers: dict[str, np.ndarray], variances: tuple[str, ...] = ()
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
            raise ValueError(
                f"denoiser input layer {name!r} has shape {np.shape(layers[name])}, "
                f"expected {expected} to match diffuse"
            )
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
