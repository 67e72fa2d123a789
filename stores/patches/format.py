"""The patch store's format: its constants and layout, errors, opening, listing, fingerprint, checksums."""

from __future__ import annotations

import hashlib
import json
import os
import re
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import zarr
from zarr.storage import LocalStore

from admc.common.layout import N_FEATURES
from admc.errors import AdmcError

FORMAT = "admc-patches"
FORMAT_VERSION = 2
SPLITS = ("train", "val", "test")
STAGING = "_staging"
SHARD_PATCHES = 256

ROW_IMAGES = {"noisy_diffuse": 3, "noisy_specular": 3, "features": N_FEATURES}
CROP_IMAGES = {"ref_diffuse": 3, "ref_specular": 3}
BASE_IMAGES = {"base_diffuse": 3, "base_specular": 3}
"""Optional row arrays (tile.oidn_base): OIDN's output for the row, what model.base = "oidn" refines."""
RAW_REF_IMAGES = {"raw_ref_diffuse": 3, "raw_ref_specular": 3}
"""Optional crop arrays of train scenes tiled with tile.clean_targets: the raw reference beside the cleaned
target, which OIDN's fine-tune learns from too (model/training/oidn_partner.py, CANDIDATES)."""
NOISE_IMAGES = {"noise_diffuse": 1, "noise_specular": 1}
"""Optional row arrays (tile.noise_maps): each branch's noise level (model/transforms.noise_forward), what
model.noise_input reads as the last feature channel. Not in LAYOUT: the root attributes (and with them the
store's fingerprint, which a training resume checks) stay those of a store without them."""
SPECULAR_ARRAYS = ("noisy_specular", "ref_specular")
REQUIRED_ROOT_ATTRS = ("transform", "patch_size")
REQUIRED_SCENE_ATTRS = ("scene_hash", "image_size", "sanitization")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")  # "+" joins a scene's constructs (room-1000001+grate)

LAYOUT = {
    "rows": "one row per (image crop, spp): noisy_*, features, spp, crop",
    "crops": "one reference entry per row (crop[r] == r as written): ref_*, origin; row r's reference is "
    "ref_*[crop[r]]",
    "noisy_diffuse": "transform.diffuse of the noisy render",
    "noisy_specular": "transform.specular",
    "features": "transform.feature_channels",
    "ref_diffuse": "transform.diffuse of the reference",
    "ref_specular": "transform.specular of the reference",
    "origin": "(y, x) of the crop in the image",
    "base_diffuse": "optional, per row: transform.diffuse of OIDN's denoised noisy diffuse (scene attr 'base')",
    "base_specular": "optional, per row: transform.specular of OIDN's denoised noisy specular",
}


class PatchStoreError(AdmcError, ValueError):
    """A patch store is missing, malformed, or does not match what the caller expects."""


_RECOVERY = "run `admc-pipe dataset` with the same config: it re-tiles the damaged scene from its cached renders"


def _damage_error(path: Path, split: str, scene_id: str, arrays: list[str], cause: str) -> PatchStoreError:
    """The one message for a damaged scene: store, split/scene, arrays, what is wrong, how to recover."""
    return PatchStoreError(
        f"patch store {path}: scene {split}/{scene_id}, array {', '.join(arrays)}: {cause}; {_RECOVERY}"
    )


@contextmanager
def _reading(path: Path, split: str, scene_id: str, array: str):
    """A damaged file (a shard index checksum, a codec or JSON error, a truncated chunk) fails with
    the store, scene and array named instead of the codec's own words."""
    try:
        yield
    except Exception as exc:
        raise _damage_error(path, split, scene_id, [array], f"cannot be decoded ({type(exc).__name__})") from exc


def _jsonable(obj: Any, what: str) -> Any:
    """The value as it will read back from zarr.json (tuples become lists), or a clear refusal."""
    try:
        return json.loads(json.dumps(obj, allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise PatchStoreError(f"{what}: not JSON-serializable ({exc})") from None


def _check_name(value: str, what: str) -> None:
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        raise PatchStoreError(f"{what} {value!r}: use letters, digits, '.', '_', '-', '+', starting alphanumeric")


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise PatchStoreError(f"split {split!r}: must be one of {SPLITS}")


def _open_root(path: Path) -> zarr.Group:
    if not exists(path):
        raise PatchStoreError(f"{path}: no patch store here (create_store first)")
    try:
        root = zarr.open_group(store=LocalStore(path, read_only=True), mode="r")
    except Exception as exc:  # zarr raises whatever its JSON or metadata parser does
        raise PatchStoreError(
            f"{path / 'zarr.json'}: the store's root metadata cannot be read ({type(exc).__name__}: "
            f"{exc}); move the store away (or delete it) and run `admc-pipe dataset` to tile it "
            "again from the cached renders"
        ) from None
    if root.attrs.get("format") != FORMAT:
        raise PatchStoreError(f"{path}: not an {FORMAT} store (format={root.attrs.get('format')!r})")
    version = root.attrs.get("format_version")
    if version != FORMAT_VERSION:
        older = isinstance(version, int) and version < FORMAT_VERSION
        raise PatchStoreError(
            f"{path}: format_version {version!r}, this code reads {FORMAT_VERSION}"
            + (
                "; written by an older admc: move it away (or delete it) and run `admc-pipe dataset` to tile "
                "it again from the cached renders"
                if older
                else ""
            )
        )
    return root


def _lookup(d: dict, dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return "<missing>"
        d = d[part]
    return d


def exists(path: str | os.PathLike) -> bool:
    """Whether a patch store was created at `path` (its format is checked when it is opened)."""
    return (Path(path) / "zarr.json").is_file()


def fingerprint(path: str | os.PathLike) -> str:
    """sha256 over the store's root attributes and every split's scene ids and scene hashes.

    Cheap (metadata only): it changes when scenes are added, removed or re-rendered, not when
    patch bytes are edited in place.
    """
    root = _open_root(Path(path))
    scenes = {
        split: {scene: root[f"{split}/{scene}"].attrs.get("scene_hash") for scene in list_scenes(path, split)}
        for split in SPLITS
    }
    text = json.dumps({"attrs": dict(root.attrs), "scenes": scenes}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def has_scene(path: str | os.PathLike, split: str, scene_id: str) -> bool:
    """True when the scene is published (complete: only whole scenes are ever renamed into place)."""
    _check_split(split)
    _check_name(scene_id, "scene_id")
    return (Path(path) / split / scene_id / "zarr.json").is_file()


def has_noise_maps(path: str | os.PathLike, split: str, scene_id: str) -> bool:
    """True when a published scene keeps noise maps (tile.noise_maps)."""
    return bool(_open_root(Path(path))[f"{split}/{scene_id}"].attrs.get("has_noise", False))


def list_scenes(path: str | os.PathLike, split: str) -> list[str]:
    """Published scenes of a split, sorted."""
    _check_split(split)
    base = Path(path) / split
    if not base.is_dir():
        return []
    return sorted(p.name for p in base.iterdir() if _NAME.fullmatch(p.name) and (p / "zarr.json").is_file())


def _array_digest(directory: Path) -> str:
    """sha256 over an array's files (names and bytes): changes with any flipped, lost or added byte."""
    digest = hashlib.sha256()
    for file in sorted(p for p in directory.rglob("*") if p.is_file()):
        digest.update(file.relative_to(directory).as_posix().encode() + b"\0")
        digest.update(file.read_bytes())
    return digest.hexdigest()


def damaged_arrays(path: str | os.PathLike, split: str, scene_id: str) -> list[str]:
    """Arrays of a published scene whose files differ from the checksums recorded when it was written
    ("zarr.json" when the scene's own metadata is unreadable). Reads every file of the scene once.
    Scenes written before checksums were recorded have nothing to compare: [].
    """
    directory = Path(path) / split / scene_id
    try:
        checksums = json.loads((directory / "zarr.json").read_bytes())["attributes"].get("checksums", {})
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return ["zarr.json"]
    return [name for name, digest in sorted(checksums.items()) if _array_digest(directory / name) != digest]
