"""EXRs as other programs write them: every part of a multipart file, any channel names, any header values.

Separate from `exr.py` (admc's own layers), whose source is part of the render tasks' code version: a
change here re-renders nothing.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
import OpenEXR

from admc.stores.atomic import publishing
from admc.stores.exr import RESERVED_ATTRIBUTES, ExrError, _open_exr


def read_channels(path: Path, names: Iterable[str] | None = None) -> tuple[dict, dict[str, np.ndarray]]:
    """Every part of an EXR: (the first part's header, {full channel name: float32 (H, W) plane}).

    Renderers write passes as separate parts of one file (Blender 5 writes one part per pass: a reader
    that opens the first part sees `ViewLayer.Combined` only), so this reads all of them. `names`
    limits which channels are converted; the header attributes are OpenEXR's Python values.
    """
    path = Path(path)
    exr = _open_exr(path, header_only=False)
    header = dict(exr.parts[0].header)
    wanted = None if names is None else set(names)
    lo, hi = header["dataWindow"]
    size = (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))
    planes = {}
    for part in exr.parts:
        try:
            part_channels = part.channels
        except (RuntimeError, ValueError) as exc:
            raise ExrError(f"{path}: truncated or corrupt EXR part {part.name()!r} ({exc})") from None
        for name, channel in part_channels.items():
            if wanted is not None and name not in wanted:
                continue
            plane = np.asarray(channel.pixels)
            if plane.shape != size:
                raise ExrError(
                    f"{path}: channel {name} is {plane.shape[0]}x{plane.shape[1]}, the image is "
                    f"{size[0]}x{size[1]} (subsampled channels and parts of other sizes are not supported)"
                )
            planes[name] = plane.astype(np.float32)
    return header, planes


def channel_names(path: Path) -> tuple[dict, list[str]]:
    """(the first part's header, every channel name of every part), reading headers only."""
    path = Path(path)
    exr = _open_exr(path, header_only=True)
    return dict(exr.parts[0].header), [c.name for part in exr.parts for c in part.header["channels"]]


def write_channels(path: Path, channels: dict[str, np.ndarray], *, attributes: dict | None = None) -> None:
    """Write float32 planes under the full channel names given (another program's layout, e.g.
    Blender's `ViewLayer.Combined.R`), atomically; `attributes` may hold any OpenEXR header value."""
    path = Path(path)
    if not channels:
        raise ExrError(f"{path}: no channels to write")
    sizes = {np.shape(a) for a in channels.values()}
    if len(sizes) != 1 or len(next(iter(sizes))) != 2:
        raise ExrError(f"{path}: channels must be 2-D planes of one size, got {sorted(map(str, sizes))}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        if key in RESERVED_ATTRIBUTES:
            raise ExrError(f"{path}: attribute {key!r} is a reserved EXR header name")
        header[key] = value
    planes = {name: np.ascontiguousarray(array, dtype=np.float32) for name, array in channels.items()}
    with publishing(path) as tmp, tmp.open("wb") as stream:
        OpenEXR.File(header, planes).write(stream)
