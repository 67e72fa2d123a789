"""Intel Open Image Denoise, called from one place: the OIDN bases of admc+oidn and the OIDN baseline.

Both go through `denoise`, so they run OIDN the same way and differ only in the quality each asks for;
`denoise_with_weights` runs OIDN's network with other weights (OIDN fine-tuned on a domain, train.oidn_minutes).
"""

from __future__ import annotations

import numpy as np

QUALITIES = ("high", "balanced", "fast")


def denoise(color, albedo=None, normal=None, *, quality: str, clean_aux: bool = False):
    """OIDN's HDR denoising of `color` (H, W, 3), guided by albedo and normal where given.

    Inputs are sanitised layers (admc.common.buffers.sanitize): OIDN expects radiance >= 0, albedo
    in [0, 1] and normals in [-1, 1], and a NaN spreads over its whole receptive field. NumPy arrays
    go to OIDN's CPU device as contiguous float32; CUDA torch tensors run on their GPU. `clean_aux`: the
    guides are noise-free (e.g. `prefilter`ed), which at quality "high" runs OIDN's large network.
    """
    import pyoidn  # here, not at the top: the config reads QUALITIES without loading OIDN's libraries

    quality = check_quality(quality)
    return pyoidn.denoise(_host(color), _host(albedo), _host(normal), hdr=True, quality=quality, clean_aux=clean_aux)


def prefilter(name: str, image):
    """OIDN's own denoising of an (H, W, 3) "albedo" or "normal" guide at quality "high" (its large guide
    networks): the first half of its final-frame route, whose second half is `denoise(..., clean_aux=True)`."""
    from pyoidn.filter import OIDN_FORMAT_FLOAT3, OIDN_QUALITY_HIGH, Filter

    image = _host(image)
    height, width = image.shape[:2]
    output = np.zeros_like(image)
    device = _device()
    with Filter(device) as oidn_filter:
        oidn_filter.set_image(name, image, OIDN_FORMAT_FLOAT3, width, height)
        oidn_filter.set_image("output", output, OIDN_FORMAT_FLOAT3, width, height)
        oidn_filter.set_quality(OIDN_QUALITY_HIGH)
        oidn_filter.commit()
        oidn_filter.execute()
        _raise_device_error(device)
    return output


def check_quality(quality: str) -> str:
    """`quality` if OIDN offers it, else a ValueError naming the choices."""
    if quality not in QUALITIES:
        raise ValueError(f"OIDN quality must be one of {', '.join(QUALITIES)}, got {quality!r}")
    return quality


def _host(image):
    """NumPy images as OIDN's CPU device reads them; None and torch tensors as they are."""
    return np.ascontiguousarray(image, dtype=np.float32) if isinstance(image, np.ndarray) else image


def denoise_with_weights(color, albedo=None, normal=None, *, weights: bytes, clean_aux: bool = False):
    """`denoise` at quality "high" with OIDN's network running other weights: `weights` is a TZA archive of
    its U-Net (stores/oidn_archives.py `write_archive`; OIDN builds the network its tensors name, standard or
    large), e.g. one fine-tuned on a domain. OIDN's C API takes it as the filter's "weights" data; pyoidn does
    not declare that call, so it is declared here."""
    from pyoidn.filter import OIDN_FORMAT_FLOAT3, OIDN_QUALITY_HIGH, Filter

    color = _host(color)
    height, width = color.shape[:2]
    output = np.zeros_like(color)
    device = _device()
    blob = _ffi().from_buffer(weights)  # OIDN reads it while the filter commits
    with Filter(device) as oidn_filter:
        for name, image in (("color", color), ("albedo", _host(albedo)), ("normal", _host(normal)), ("output", output)):
            if image is not None:
                oidn_filter.set_image(name, image, OIDN_FORMAT_FLOAT3, width, height)
        oidn_filter.set_bool("hdr", True)
        oidn_filter.set_bool("cleanAux", clean_aux)
        oidn_filter.set_quality(OIDN_QUALITY_HIGH)
        _capi().oidnSetSharedFilterData(oidn_filter._filter, b"weights", blob, len(weights))
        oidn_filter.commit()
        oidn_filter.execute()
        _raise_device_error(device)
    return output


_DEVICE = None


def _ffi():
    from pyoidn.capi import oidn_ffi

    if not getattr(oidn_ffi, "_admc_filter_data", False):
        oidn_ffi.cdef(
            "void oidnSetSharedFilterData(OIDNFilter filter, const char* name, void* hostPtr, size_t byteSize);"
        )
        oidn_ffi._admc_filter_data = True
    return oidn_ffi


def _capi():
    from pyoidn.capi import oidn_Capi

    _ffi()
    return oidn_Capi


def _device():
    """One committed CPU device per process, as pyoidn keeps its own."""
    global _DEVICE
    if _DEVICE is None:
        from pyoidn.device import Device

        device = Device()
        device.commit()
        _raise_device_error(device)
        _DEVICE = device
    return _DEVICE


def _raise_device_error(device) -> None:
    from pyoidn.denoise import _check_error

    _check_error(device, "denoising with fine-tuned weights")
