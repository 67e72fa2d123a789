"""Intel Open Image Denoise, called from one place: the OIDN bases of admc+oidn and the OIDN baseline.

Both go through `denoise`, so they run OIDN the same way and differ only in the quality each asks for.
"""

from __future__ import annotations

import numpy as np

QUALITIES = ("high", "balanced", "fast")


def denoise(color, albedo=None, normal=None, *, quality: str):
    """OIDN's HDR denoising of `color` (H, W, 3), guided by albedo and normal where given.

    Inputs are sanitised layers (admc.common.buffers.sanitize): OIDN expects radiance >= 0, albedo
    in [0, 1] and normals in [-1, 1], and a NaN spreads over its whole receptive field. NumPy arrays
    go to OIDN's CPU device as contiguous float32; CUDA torch tensors run on their GPU.
    """
    import pyoidn  # here, not at the top: the config reads QUALITIES without loading OIDN's libraries

    return pyoidn.denoise(_host(color), _host(albedo), _host(normal), hdr=True, quality=check_quality(quality))


def check_quality(quality: str) -> str:
    """`quality` if OIDN offers it, else a ValueError naming the choices."""
    if quality not in QUALITIES:
        raise ValueError(f"OIDN quality must be one of {', '.join(QUALITIES)}, got {quality!r}")
    return quality


def _host(image):
    """NumPy images as OIDN's CPU device reads them; None and torch tensors as they are."""
    return np.ascontiguousarray(image, dtype=np.float32) if isinstance(image, np.ndarray) else image
