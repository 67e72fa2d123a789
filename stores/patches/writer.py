"""Writing the patch store: create it, write (or replace) one scene atomically, discard leftovers."""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import BloscCodec, BloscShuffle
from zarr.storage import LocalStore

from admc.common.diff import differing_keys
from admc.stores.atomic import fsync_path
from admc.stores.patches.format import (
    BASE_IMAGES,
    CROP_IMAGES,
    FORMAT,
    FORMAT_VERSION,
    LAYOUT,
    NOISE_IMAGES,
    RAW_REF_IMAGES,
    REQUIRED_ROOT_ATTRS,
    REQUIRED_SCENE_ATTRS,
    ROW_IMAGES,
    SHARD_PATCHES,
    SPECULAR_ARRAYS,
    SPLITS,
    STAGING,
    PatchStoreError,
    _array_digest,
    _check_name,
    _check_split,
    _jsonable,
    _lookup,
    _open_root,
    exists,
    list_scenes,
)


def _compressor() -> BloscCodec:
    return BloscCodec(cname="zstd", clevel=3, shuffle=BloscShuffle.bitshuffle)


def create_store(path: str | os.PathLike, attrs: dict) -> None:
    """Create the root and split groups; a no-op if a store with the same attributes exists.

    `attrs` must hold "transform" (the transform spec) and "patch_size"; other keys (code version,
    render fingerprint, normalisation statistics...) are stored as given. An existing store whose
    attributes differ is refused with the differing keys named, so a corpus never mixes transforms.
    A layout description that only gained entries (optional arrays documented by newer code, e.g. the
    OIDN bases) is brought up to date in place: what the scenes hold is unchanged.
    """
    path = Path(path)
    for key in REQUIRED_ROOT_ATTRS:
        if key not in attrs:
            raise PatchStoreError(f"create_store {path}: attrs lack required key {key!r}")
    if not isinstance(attrs["patch_size"], int) or attrs["patch_size"] <= 0:
        raise PatchStoreError(f"create_store {path}: patch_size must be a positive int, got {attrs['patch_size']!r}")
    reserved = {"format", "format_version", "layout"} & set(attrs)
    if reserved:
        raise PatchStoreError(f"create_store {path}: attrs may not set reserved keys {sorted(reserved)}")
    full = _jsonable(
        {**attrs, "format": FORMAT, "format_version": FORMAT_VERSION, "layout": LAYOUT}, f"create_store {path}: attrs"
    )
    if not exists(path) and (path.is_file() or (path.is_dir() and any(path.iterdir()))):
        raise PatchStoreError(
            f"{path}: exists and is not a patch store (no zarr.json); a store is made only in a "
            "new or empty folder: choose another tile.store, or move that folder away"
        )
    if exists(path):
        existing = dict(_open_root(path).attrs)
        diff = differing_keys(existing, full)
        documented_later = [k for k in diff if k.startswith("layout.") and k.split(".", 1)[1] not in existing["layout"]]
        if diff and diff == documented_later:
            zarr.open_group(store=LocalStore(path), mode="r+").attrs.put(full)
            return
        if diff and any(list_scenes(path, split) for split in SPLITS):
            raise PatchStoreError(
                f"{path}: existing store differs in {', '.join(diff)} "
                f"(e.g. {diff[0]}: store has {_lookup(existing, diff[0])!r}, asked {_lookup(full, diff[0])!r}); "
                "its scenes were tiled with those settings: use another store (tile.store) or move this one away"
            )
        if diff:  # no scene was ever published: nothing pins the old settings
            zarr.open_group(store=LocalStore(path), mode="r+").attrs.put(full)
        return
    root = zarr.open_group(store=LocalStore(path), mode="a", attributes=full)
    for name in (*SPLITS, STAGING):
        root.require_group(name)


def _validate_arrays(arrays: dict[str, np.ndarray], patch: int, where: str) -> dict[str, np.ndarray]:
    known = {*ROW_IMAGES, *CROP_IMAGES, *RAW_REF_IMAGES, *BASE_IMAGES, *NOISE_IMAGES, "spp", "crop", "origin"}
    unknown = set(arrays) - known
    if unknown:
        raise PatchStoreError(f"{where}: unknown arrays {sorted(unknown)} (known: {sorted(known)})")
    specular = [name for name in SPECULAR_ARRAYS if name in arrays]
    required = ["noisy_diffuse", "features", "ref_diffuse", "spp", "crop", "origin"]
    if specular:
        required += list(SPECULAR_ARRAYS)
    for kind, images in (("base", BASE_IMAGES), ("noise", NOISE_IMAGES), ("raw_ref", RAW_REF_IMAGES)):  # every branch
        if any(name in arrays for name in images):
            required += [f"{kind}_diffuse"] + ([f"{kind}_specular"] if specular else [])
            if f"{kind}_specular" in arrays and not specular:
                raise PatchStoreError(f"{where}: {kind}_specular given for a scene without specular arrays")
    for name in required:
        if name not in arrays:
            raise PatchStoreError(f"{where}: missing array {name!r}")
    n = len(arrays["spp"])
    m = len(arrays["origin"])
    if n == 0 or m == 0:
        raise PatchStoreError(f"{where}: a scene needs at least one row and one crop (got {n} rows, {m} crops)")
    out = {}
    for name, channels in {**ROW_IMAGES, **BASE_IMAGES, **NOISE_IMAGES, **CROP_IMAGES, **RAW_REF_IMAGES}.items():
        if name not in arrays:
            continue
        a = np.asarray(arrays[name])
        want = ((m if name in CROP_IMAGES or name in RAW_REF_IMAGES else n), channels, patch, patch)
        if a.shape != want:
            raise PatchStoreError(f"{where}: {name} has shape {a.shape}, expected {want}")
        if a.dtype not in (np.float16, np.float32, np.float64):
            raise PatchStoreError(f"{where}: {name} has dtype {a.dtype}, expected float16")
        with np.errstate(over="ignore"):
            a16 = a.astype(np.float16)
        bad = int(a16.size - np.count_nonzero(np.isfinite(a16)))
        if bad:
            raise PatchStoreError(
                f"{where}: {name} has {bad} values that are not finite in float16 (sanitize and to_fp16 before writing)"
            )
        out[name] = a16
    for name, shape in {"spp": (n,), "crop": (n,), "origin": (m, 2)}.items():
        a = np.asarray(arrays[name])
        if a.shape != shape or not np.issubdtype(a.dtype, np.integer):
            raise PatchStoreError(f"{where}: {name} must be an integer array of shape {shape}, got {a.dtype} {a.shape}")
        out[name] = a.astype(np.int32)
    if out["crop"].min() < 0 or out["crop"].max() >= m:
        raise PatchStoreError(
            f"{where}: crop indices must lie in [0, {m}), got [{out['crop'].min()}, {out['crop'].max()}]"
        )
    if out["spp"].min() <= 0:
        raise PatchStoreError(f"{where}: spp must be positive, got {out['spp'].min()}")
    return out


def _write_group(directory: Path, arrays: dict[str, np.ndarray], attrs: dict) -> None:
    group = zarr.open_group(store=LocalStore(directory), mode="w", attributes=attrs)
    for name, data in arrays.items():
        if data.ndim == 4:
            shard = min(len(data), SHARD_PATCHES)
            arr = group.create_array(
                name,
                shape=data.shape,
                dtype="float16",
                chunks=(1, *data.shape[1:]),
                shards=(shard, *data.shape[1:]),
                compressors=_compressor(),
                fill_value=0,
                dimension_names=("patch", "channel", "y", "x"),
            )
        else:
            arr = group.create_array(
                name, shape=data.shape, dtype="int32", chunks=data.shape, compressors=_compressor(), fill_value=0
            )
        arr[...] = data
    group.attrs["checksums"] = {name: _array_digest(directory / name) for name in arrays}


def write_scene(
    path: str | os.PathLike, split: str, scene_id: str, arrays: dict[str, np.ndarray], scene_attrs: dict
) -> None:
    """Write (or replace) one scene's patches; readers see the old scene or the whole new one.

    The group is written under `_staging/`, flushed, then renamed into the split. Replacing an
    existing scene moves the old one aside first: between those two renames the scene is briefly
    absent, never half-written. LocalStore only (the rename is a directory rename).
    """
    path = Path(path)
    _check_split(split)
    _check_name(scene_id, "scene_id")
    root = _open_root(path)
    where = f"write_scene {path} {split}/{scene_id}"
    for key in REQUIRED_SCENE_ATTRS:
        if key not in scene_attrs:
            raise PatchStoreError(f"{where}: scene_attrs lack required key {key!r}")
    data = _validate_arrays(arrays, root.attrs["patch_size"], where)
    attrs = _jsonable(
        {
            **scene_attrs,
            "scene_id": scene_id,
            "has_specular": "noisy_specular" in data,
            "has_base": "base_diffuse" in data,
            **({"has_noise": True} if "noise_diffuse" in data else {}),  # absent without: attributes as before
            **({"has_raw_references": True} if "raw_ref_diffuse" in data else {}),
            "n_rows": len(data["spp"]),
            "n_crops": len(data["origin"]),
            "spp_levels": sorted({int(s) for s in data["spp"]}),
        },
        f"{where}: scene_attrs",
    )

    staging = path / STAGING / f"{split}.{scene_id}.{uuid.uuid4().hex}"
    final = path / split / scene_id
    try:
        _write_group(staging, data, attrs)
        for file in staging.rglob("*"):
            if file.is_file():
                fsync_path(file)
        _publish(staging, final)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    fsync_path(final.parent)


def _publish(staging: Path, final: Path) -> None:
    """Rename `staging` onto `final`, moving an existing `final` aside (retrying if another writer of
    the same scene races us: the last rename wins, as with a plain file replace)."""
    last: OSError | None = None
    for _ in range(8):
        try:
            os.rename(staging, final)
            return
        except OSError as exc:
            last = exc
            if not final.exists():
                continue
            trash = staging.with_name(f"trash.{uuid.uuid4().hex}")
            try:
                os.rename(final, trash)
            except FileNotFoundError:
                continue
            shutil.rmtree(trash, ignore_errors=True)
    raise PatchStoreError(f"{final}: could not publish the scene ({last})")


def discard_staging(path: str | os.PathLike) -> int:
    """Delete what killed writers left in `_staging/`; call only when no writer is running."""
    staging = Path(path) / STAGING
    left = [p for p in staging.iterdir() if p.is_dir()] if staging.is_dir() else []
    for p in left:
        shutil.rmtree(p)
    return len(left)
