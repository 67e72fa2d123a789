"""OIDN's own trained weights: the Tensor Archive (TZA) files its library carries, read as float32 arrays.

Intel Open Image Denoise ships its networks' weights inside its core library as TZA archives (the format of
RenderKit/oidn `training/tza.py`: a magic number, a table of named tensors, each aligned in the file). They are
Apache-2.0 like the library. admc reads them from the installed pyoidn, so fine-tuning OIDN's own network on a
domain starts from exactly the weights OIDN runs; nothing is copied into this repository.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from admc.errors import AdmcError

TZA_MAGIC = b"\xd7\x41\x02"  # 0x41D7 little-endian, format version 2.x
_DTYPES = {"f": np.float32, "h": np.float16}


class ArchiveError(AdmcError, ValueError):
    """An OIDN weight archive or library cannot be read; the message names the file."""


def read_archive(data: bytes, start: int = 0, source: str = "archive") -> dict[str, np.ndarray]:
    """{tensor name: float32 array} of the TZA archive at byte `start` of `data` (a .tza file or a library)."""
    try:
        if data[start : start + 3] != TZA_MAGIC:
            raise ValueError("no TZA header")
        (table,) = struct.unpack_from("<Q", data, start + 4)
        pos = start + table
        (count,) = struct.unpack_from("<I", data, pos)
        pos += 4
        tensors = {}
        for _ in range(count):
            (length,) = struct.unpack_from("<H", data, pos)
            name = data[pos + 2 : pos + 2 + length].decode()
            pos += 2 + length
            ndims = data[pos]
            shape = struct.unpack_from(f"<{ndims}I", data, pos + 1)
            pos += 1 + 4 * ndims + ndims  # shape, then the layout's letters
            dtype = _DTYPES[chr(data[pos])]
            (offset,) = struct.unpack_from("<Q", data, pos + 1)
            pos += 9
            size = int(np.prod(shape))
            if start + offset + size * np.dtype(dtype).itemsize > len(data):
                raise ValueError(f"tensor {name!r} runs past the end")
            tensors[name] = np.frombuffer(data, dtype, size, start + offset).reshape(shape).astype(np.float32)
        return tensors
    except (ValueError, KeyError, struct.error, UnicodeDecodeError, IndexError, OverflowError) as exc:
        raise ArchiveError(f"{source}: not a readable OIDN weight archive at byte {start} ({exc})") from exc


def write_archive(tensors: dict[str, np.ndarray]) -> bytes:
    """A TZA archive (float16, OIDN's layout names) of a network's tensors: what OIDN's filter takes as its
    "weights" and what `admc-pipe export` writes for a fine-tuned OIDN."""
    out = bytearray(struct.pack("<HBBQ", 0x41D7, 2, 0, 0))
    table = []
    for name, tensor in tensors.items():
        out += bytes(-len(out) % 64)
        table.append((name, tensor.shape, len(out)))
        out += np.ascontiguousarray(tensor, dtype=np.float16).tobytes()
    out += bytes(-len(out) % 64)
    out[4:12] = struct.pack("<Q", len(out))
    out += struct.pack("<I", len(table))
    for name, shape, offset in table:
        encoded, layout = name.encode(), "oihw" if len(shape) == 4 else "x"
        out += struct.pack(f"<H{len(encoded)}sB{len(shape)}I", len(encoded), encoded, len(shape), *shape)
        out += layout.encode() + b"h" + struct.pack("<Q", offset)
    return bytes(out)


def library_archives(library: Path | None = None) -> list[dict[str, np.ndarray]]:
    """Every weight archive in OIDN's core library (the installed pyoidn's unless `library` is named), in the
    library's order. Which archive is which filter's is not recorded there: model/nets/oidn_unet.py tells them
    apart by what OIDN itself computes."""
    path = Path(library) if library else _installed_core_library()
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ArchiveError(f"{path}: cannot read OIDN's library ({exc.strerror or exc})") from exc
    archives, pos = [], 0
    while (start := data.find(TZA_MAGIC, pos)) >= 0:
        pos = start + 1
        try:
            archive = read_archive(data, start, str(path))
        except ArchiveError:
            continue  # the magic bytes occur in code too
        if archive:
            archives.append(archive)
    if not archives:
        raise ArchiveError(f"{path}: no OIDN weight archive found in this library")
    return archives


def _installed_core_library() -> Path:
    import pyoidn

    root = Path(pyoidn.__file__).parent / "oidn"
    found = [p for p in sorted(root.glob("*/*OpenImageDenoise_core*")) if not p.is_symlink()]
    if not found:
        raise ArchiveError(f"{root}: pyoidn has no OpenImageDenoise_core library")
    return max(found, key=lambda p: p.stat().st_size)
