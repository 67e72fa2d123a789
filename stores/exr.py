"""Multi-layer EXR files of admc renders (OpenEXR 3.5) and single images of any format (OpenImageIO).

One EXR per (scene, spp) holds every buffer as `layer.channel` (e.g. `diffuse.R`, `normal.X`).
Noisy renders are stored in half precision, references in float. Every failure raises ExrError
naming the file and what is wrong, so a bad file in a corpus of thousands is found at once.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import OpenEXR
import OpenImageIO as oiio

from admc.common.buffers import LAYERS
from admc.common.layout import FP16_MAX
from admc.errors import AdmcError
from admc.stores.atomic import publishing

# Layers where a negative value means a broken render (normals are legitimately negative).
NONNEGATIVE_LAYERS = frozenset(name for name, layer in LAYERS.items() if layer.low >= 0)
PRECISIONS = {"half": np.float16, "float": np.float32}
# Header attributes OpenEXR manages itself: user attributes must not shadow them.
RESERVED_ATTRIBUTES = frozenset(
    {
        "channels",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "type",
        "tiles",
        "name",
        "version",
        "chunkCount",
    }
)
EXR_MAGIC = b"\x76\x2f\x31\x01"
KNOWN_MAGIC = {
    b"\x89PNG": "a PNG image",
    b"\xff\xd8\xff": "a JPEG image",
    b"#?RA": "a Radiance HDR image",
    b"#?RG": "a Radiance HDR image",
    b"PF\n": "a PFM image",
    b"Pf\n": "a PFM image",
    b"II*\x00": "a TIFF image",
    b"MM\x00*": "a TIFF image",
}


class ExrError(AdmcError, ValueError):
    """An image file is missing, unreadable, or does not hold what was asked for."""


def write_exr(
    path: Path, layers: dict[str, np.ndarray], *, precision: str = "half", attributes: dict[str, str] | None = None
) -> None:
    """Write `layers` (name -> (H, W, C) array) to one EXR, atomically (temp name, then rename).

    Half precision refuses finite values beyond +-65504 (they would silently become inf): sanitize
    them first, or write references with precision="float".
    """
    path = Path(path)
    if precision not in PRECISIONS:
        raise ExrError(f"{path}: precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
    dtype = PRECISIONS[precision]
    _check_layers(path, layers)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        if key in RESERVED_ATTRIBUTES or not isinstance(value, str):
            raise ExrError(f"{path}: attribute {key!r} must be a str that is not a reserved EXR header name")
        header[key] = value
    channels = {}
    for name, array in layers.items():
        with np.errstate(over="ignore", invalid="ignore"):
            stored = np.asarray(array).astype(dtype)
        overflow = np.isinf(stored) & np.isfinite(array)
        if overflow.any():
            raise ExrError(
                f"{path}: layer {name!r} has {int(overflow.sum())} finite values beyond "
                f"+-{FP16_MAX:g} that half precision would turn into inf; clamp them or use "
                f"precision='float'"
            )
        for i, channel in enumerate(LAYERS[name].channels):
            channels[_full_name(name, channel)] = np.ascontiguousarray(stored[:, :, i])
    with publishing(path) as tmp, tmp.open("wb") as stream:  # through Python: a full disk raises OSError
        OpenEXR.File(header, channels).write(stream)


def _check_layers(path: Path, layers: dict[str, np.ndarray]) -> None:
    if not layers:
        raise ExrError(f"{path}: no layers to write")
    sizes = {}
    for name, array in layers.items():
        if name not in LAYERS:
            raise ExrError(f"{path}: unknown layer {name!r}; known layers: {', '.join(LAYERS)}")
        expected = len(LAYERS[name].channels)
        shape = np.shape(array)
        if len(shape) != 3 or shape[2] != expected:
            raise ExrError(f"{path}: layer {name!r} must be (H, W, {expected}), got shape {shape}")
        if not np.issubdtype(np.asarray(array).dtype, np.floating):
            raise ExrError(f"{path}: layer {name!r} must be a float array, got {np.asarray(array).dtype}")
        sizes[name] = shape[:2]
    if len(set(sizes.values())) > 1:
        raise ExrError(f"{path}: layers differ in size: {sizes}")


def _open_exr(path: Path, header_only: bool) -> OpenEXR.File:
    """Open with checks that turn OpenEXR's generic failures into messages that say what is wrong."""
    if not path.is_file():
        raise ExrError(f"{path}: no such file")
    with open(path, "rb") as f:
        start = f.read(4)
    if start != EXR_MAGIC:
        kind = next((what for magic, what in KNOWN_MAGIC.items() if start.startswith(magic)), None)
        raise ExrError(f"{path}: not an OpenEXR file" + (f" (it is {kind})" if kind else f" (starts with {start!r})"))
    try:
        exr = OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
        if not header_only:
            exr.channels()  # a truncated file has no readable part
    except (RuntimeError, ValueError) as exc:
        raise ExrError(f"{path}: truncated or corrupt EXR ({exc})") from None
    return exr


def _channel_names(exr: OpenEXR.File) -> list[str]:
    return [channel.name for channel in exr.header()["channels"]]


def _full_name(layer: str, channel: str) -> str:
    return f"{layer}.{channel}" if layer else channel


def _group_layers(channel_names: Iterable[str]) -> dict[str, list[str]]:
    """'diffuse.R' -> {'diffuse': ['R']}; channels without a layer prefix form the beauty layer ''."""
    grouped: dict[str, list[str]] = {}
    for full in channel_names:
        layer, _, channel = full.rpartition(".")
        grouped.setdefault(layer, []).append(channel)
    return grouped


def exr_layers(path: Path) -> list[str]:
    """Layer names present in an EXR (reads the header only)."""
    path = Path(path)
    return sorted(_group_layers(_channel_names(_open_exr(path, header_only=True))))


def read_exr(path: Path, layers: list[str] | None = None) -> dict[str, np.ndarray]:
    """Read admc layers as float32 (H, W, C) arrays: the requested ones, or every known layer present."""
    path = Path(path)
    exr = _open_exr(path, header_only=False)
    names = _channel_names(exr)
    present = _group_layers(names)
    if layers is None:
        layers = [name for name in LAYERS if name in present]
        if not layers:
            raise ExrError(f"{path}: holds no admc layer (channels: {', '.join(names)})")
    for name in layers:
        if name not in LAYERS:
            raise ExrError(f"{path}: unknown layer {name!r}; known layers: {', '.join(LAYERS)}")
        if name not in present:
            holds = ", ".join(sorted(present)) or f"no layers, only channels {', '.join(names)}"
            raise ExrError(f"{path}: has no layer {name!r}; it holds {holds}")
        missing = [c for c in LAYERS[name].channels if c not in present[name]]
        if missing:
            raise ExrError(
                f"{path}: layer {name!r} lacks channel(s) {', '.join(missing)} (has {', '.join(present[name])})"
            )
    lo, hi = exr.header()["dataWindow"]
    size = (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))
    pixels = exr.channels()
    out = {}
    for name in layers:
        planes = []
        for channel in LAYERS[name].channels:
            plane = pixels[_full_name(name, channel)].pixels
            if plane.shape != size:
                raise ExrError(
                    f"{path}: channel {name}.{channel} is {plane.shape[0]}x{plane.shape[1]}, "
                    f"the image is {size[0]}x{size[1]} (subsampled channels are not supported)"
                )
            planes.append(plane.astype(np.float32))
        out[name] = np.stack(planes, axis=-1)
    return out


def read_image(path: Path) -> np.ndarray:
    """Read any image OpenImageIO knows (EXR, HDR, PFM, PNG, ...) as float32 (H, W, C), top row first.

    Values are as stored: 8-bit formats come back in [0, 1] without undoing their sRGB encoding.
    """
    path = Path(path)
    if not path.is_file():
        raise ExrError(f"{path}: no such file")
    config = oiio.ImageSpec()
    config.attribute("pnm:pfmflip", 1)  # PFM stores the bottom row first; without this OIIO returns it first
    image = oiio.ImageInput.open(str(path), config)
    if image is None:
        raise ExrError(f"{path}: OpenImageIO cannot open it ({oiio.geterror()})")
    try:
        spec = image.spec()
        pixels = image.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise ExrError(f"{path}: OpenImageIO failed to read the pixels ({image.geterror()})")
    finally:
        image.close()
    pixels = np.asarray(pixels, dtype=np.float32)
    return pixels.reshape(spec.height, spec.width, spec.nchannels)


def nonfinite_report(
    layers: dict[str, np.ndarray], negative_layers: Iterable[str] = NONNEGATIVE_LAYERS
) -> dict[str, dict[str, int]]:
    """Count NaN, +inf, -inf (and negatives where they are invalid) per layer; only layers with any."""
    negative_layers = frozenset(negative_layers)
    report = {}
    for name, array in layers.items():
        array = np.asarray(array)
        counts = {
            "nan": int(np.isnan(array).sum()),
            "posinf": int(np.isposinf(array).sum()),
            "neginf": int(np.isneginf(array).sum()),
            "negative": int((np.isfinite(array) & (array < 0)).sum()) if name in negative_layers else 0,
        }
        if any(counts.values()):
            report[name] = counts
    return report
