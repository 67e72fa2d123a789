"""The Zarr v3 patch store: FP16 128x128 training patches, one group per scene, lock-free writers.

Layout (LocalStore directory):

    root/                      attrs: format, format_version, patch_size, transform, layout, caller's keys
      _staging/                scenes being written (and replaced scenes being deleted); never read
      train/ val/ test/        one group per split
        <scene_id>/            one group per scene, written by one task; attrs: scene_id, scene_hash,
                               has_specular, image_size, sanitization, n_rows, n_crops (= n_rows),
                               checksums (sha256 of each array's files, as written)
          noisy_diffuse  (n, 3, P, P) f16   one row per (image crop, spp)
          noisy_specular (n, 3, P, P) f16   only for scenes with specular
          features       (n, 7, P, P) f16   rendered at the row's spp, so per row
          spp            (n,)  int32
          crop           (n,)  int32        row -> its reference entry; the tile stage writes the identity
          ref_diffuse    (n, 3, P, P) f16   one per row: demodulated by that row's own albedo
          ref_specular   (n, 3, P, P) f16   only with specular
          origin         (n, 2) int32       the row's (y, x) in the image

Why this shape: a scene group is written whole by one task, so parallel writers never share a
chunk, shard or metadata file (no locks), and adding a scene adds a group without rewriting
anything. The scene list is therefore not kept in the root attributes (that would be a
read-modify-write by every writer); it is the split group's directory listing. A scene is staged
under `_staging/` and renamed into its split last, so a killed writer never leaves a half scene
visible. Each row has its own reference entry: the reference diffuse is divided by the row's own
(noisy) albedo, the albedo inference has, so it cannot be shared between the spp levels of an image
crop. The reader still goes through the `crop` index (tiny, read once per scene); the tile stage
writes it as the identity, so n_crops equals n_rows (format_version 2; version 1 promised one
shared reference per image crop and is refused).
Image arrays have chunks of exactly one patch (a random read decodes one patch) grouped into
shards of up to SHARD_PATCHES patches (few files per scene). Zarr checksums only a shard's index:
flipped bytes inside a compressed chunk mostly decode to wrong values without any error, so each
scene records a checksum per array and `damaged_arrays` compares them.
"""
from __future__ import annotations

import bisect
import hashlib
import json
import os
import re
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.codecs import BloscCodec, BloscShuffle
from zarr.storage import LocalStore

from admc.common.diff import differing_keys
from admc.common.layout import BRANCHES, N_FEATURES
from admc.errors import AdmcError
from admc.stores.atomic import fsync_path

FORMAT = "admc-patches"
FORMAT_VERSION = 2
SPLITS = ("train", "val", "test")
STAGING = "_staging"
SHARD_PATCHES = 256

ROW_IMAGES = {"noisy_diffuse": 3, "noisy_specular": 3, "features": N_FEATURES}
CROP_IMAGES = {"ref_diffuse": 3, "ref_specular": 3}
SPECULAR_ARRAYS = ("noisy_specular", "ref_specular")
REQUIRED_ROOT_ATTRS = ("transform", "patch_size")
REQUIRED_SCENE_ATTRS = ("scene_hash", "image_size", "sanitization")
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")

LAYOUT = {
    "rows": "one row per (image crop, spp): noisy_*, features, spp, crop",
    "crops": "one reference entry per row (crop[r] == r as written): ref_*, origin; row r's reference is "
             "ref_*[crop[r]]",
    "noisy_diffuse": "transform.diffuse of the noisy render", "noisy_specular": "transform.specular",
    "features": "transform.feature_channels", "ref_diffuse": "transform.diffuse of the reference",
    "ref_specular": "transform.specular of the reference", "origin": "(y, x) of the crop in the image",
}


class PatchStoreError(AdmcError, ValueError):
    """A patch store is missing, malformed, or does not match what the caller expects."""


_RECOVERY = "run `admc-pipe dataset` with the same config: it re-tiles the damaged scene from its cached renders"


def _damage_error(path: Path, split: str, scene_id: str, arrays: list[str], cause: str) -> PatchStoreError:
    """The one message for a damaged scene: store, split/scene, arrays, what is wrong, how to recover."""
    return PatchStoreError(f"patch store {path}: scene {split}/{scene_id}, array {', '.join(arrays)}: {cause}; "
                           f"{_RECOVERY}")


@contextmanager
def _reading(path: Path, split: str, scene_id: str, array: str):
    """A damaged file (a shard index checksum, a codec or JSON error, a truncated chunk) fails with
    the store, scene and array named instead of the codec's own words."""
    try:
        yield
    except Exception as exc:
        raise _damage_error(path, split, scene_id, [array], f"cannot be decoded ({type(exc).__name__})") from exc


def _compressor() -> BloscCodec:
    return BloscCodec(cname="zstd", clevel=3, shuffle=BloscShuffle.bitshuffle)


def _jsonable(obj: Any, what: str) -> Any:
    """The value as it will read back from zarr.json (tuples become lists), or a clear refusal."""
    try:
        return json.loads(json.dumps(obj, allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise PatchStoreError(f"{what}: not JSON-serializable ({exc})") from None


def _check_name(value: str, what: str) -> None:
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        raise PatchStoreError(f"{what} {value!r}: use letters, digits, '.', '_', '-', starting alphanumeric")


def _check_split(split: str) -> None:
    if split not in SPLITS:
        raise PatchStoreError(f"split {split!r}: must be one of {SPLITS}")


def _open_root(path: Path) -> zarr.Group:
    if not exists(path):
        raise PatchStoreError(f"{path}: no patch store here (create_store first)")
    root = zarr.open_group(store=LocalStore(path, read_only=True), mode="r")
    if root.attrs.get("format") != FORMAT:
        raise PatchStoreError(f"{path}: not an {FORMAT} store (format={root.attrs.get('format')!r})")
    version = root.attrs.get("format_version")
    if version != FORMAT_VERSION:
        older = isinstance(version, int) and version < FORMAT_VERSION
        raise PatchStoreError(
            f"{path}: format_version {version!r}, this code reads {FORMAT_VERSION}"
            + ("; written by an older admc: move it away (or delete it) and run `admc-pipe dataset` to tile "
               "it again from the cached renders" if older else ""))
    return root


def exists(path: str | os.PathLike) -> bool:
    """Whether a patch store was created at `path` (its format is checked when it is opened)."""
    return (Path(path) / "zarr.json").is_file()


def fingerprint(path: str | os.PathLike) -> str:
    """sha256 over the store's root attributes and every split's scene ids and scene hashes.

    Cheap (metadata only): it changes when scenes are added, removed or re-rendered, not when
    patch bytes are edited in place.
    """
    root = _open_root(Path(path))
    scenes = {split: {scene: root[f"{split}/{scene}"].attrs.get("scene_hash") for scene in list_scenes(path, split)}
              for split in SPLITS}
    text = json.dumps({"attrs": dict(root.attrs), "scenes": scenes}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def create_store(path: str | os.PathLike, attrs: dict) -> None:
    """Create the root and split groups; a no-op if a store with the same attributes exists.

    `attrs` must hold "transform" (the transform spec) and "patch_size"; other keys (code version,
    render fingerprint, normalisation statistics...) are stored as given. An existing store whose
    attributes differ is refused with the differing keys named, so a corpus never mixes transforms.
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
    full = _jsonable({**attrs, "format": FORMAT, "format_version": FORMAT_VERSION, "layout": LAYOUT},
                     f"create_store {path}: attrs")
    if exists(path):
        existing = dict(_open_root(path).attrs)
        diff = differing_keys(existing, full)
        if diff and any(list_scenes(path, split) for split in SPLITS):
            raise PatchStoreError(
                f"{path}: existing store differs in {', '.join(diff)} "
                f"(e.g. {diff[0]}: store has {_lookup(existing, diff[0])!r}, asked {_lookup(full, diff[0])!r}); "
                "its scenes were tiled with those settings: use another store (tile.store) or move this one away")
        if diff:  # no scene was ever published: nothing pins the old settings
            zarr.open_group(store=LocalStore(path), mode="r+").attrs.put(full)
        return
    root = zarr.open_group(store=LocalStore(path), mode="a", attributes=full)
    for name in (*SPLITS, STAGING):
        root.require_group(name)


def _lookup(d: dict, dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return "<missing>"
        d = d[part]
    return d


def _validate_arrays(arrays: dict[str, np.ndarray], patch: int, where: str) -> dict[str, np.ndarray]:
    known = {*ROW_IMAGES, *CROP_IMAGES, "spp", "crop", "origin"}
    unknown = set(arrays) - known
    if unknown:
        raise PatchStoreError(f"{where}: unknown arrays {sorted(unknown)} (known: {sorted(known)})")
    specular = [name for name in SPECULAR_ARRAYS if name in arrays]
    required = ["noisy_diffuse", "features", "ref_diffuse", "spp", "crop", "origin"]
    if specular:
        required += list(SPECULAR_ARRAYS)
    for name in required:
        if name not in arrays:
            raise PatchStoreError(f"{where}: missing array {name!r}")
    n = len(arrays["spp"])
    m = len(arrays["origin"])
    if n == 0 or m == 0:
        raise PatchStoreError(f"{where}: a scene needs at least one row and one crop (got {n} rows, {m} crops)")
    out = {}
    for name, channels in {**ROW_IMAGES, **CROP_IMAGES}.items():
        if name not in arrays:
            continue
        a = np.asarray(arrays[name])
        want = ((n if name in ROW_IMAGES else m), channels, patch, patch)
        if a.shape != want:
            raise PatchStoreError(f"{where}: {name} has shape {a.shape}, expected {want}")
        if a.dtype not in (np.float16, np.float32, np.float64):
            raise PatchStoreError(f"{where}: {name} has dtype {a.dtype}, expected float16")
        with np.errstate(over="ignore"):
            a16 = a.astype(np.float16)
        bad = int(a16.size - np.count_nonzero(np.isfinite(a16)))
        if bad:
            raise PatchStoreError(f"{where}: {name} has {bad} values that are not finite in float16 "
                                  "(sanitize and to_fp16 before writing)")
        out[name] = a16
    for name, shape in {"spp": (n,), "crop": (n,), "origin": (m, 2)}.items():
        a = np.asarray(arrays[name])
        if a.shape != shape or not np.issubdtype(a.dtype, np.integer):
            raise PatchStoreError(f"{where}: {name} must be an integer array of shape {shape}, got {a.dtype} {a.shape}")
        out[name] = a.astype(np.int32)
    if out["crop"].min() < 0 or out["crop"].max() >= m:
        raise PatchStoreError(f"{where}: crop indices must lie in [0, {m}), got [{out['crop'].min()}, {out['crop'].max()}]")
    if out["spp"].min() <= 0:
        raise PatchStoreError(f"{where}: spp must be positive, got {out['spp'].min()}")
    return out


def _write_group(directory: Path, arrays: dict[str, np.ndarray], attrs: dict) -> None:
    group = zarr.open_group(store=LocalStore(directory), mode="w", attributes=attrs)
    for name, data in arrays.items():
        if data.ndim == 4:
            shard = min(len(data), SHARD_PATCHES)
            arr = group.create_array(
                name, shape=data.shape, dtype="float16", chunks=(1, *data.shape[1:]),
                shards=(shard, *data.shape[1:]), compressors=_compressor(), fill_value=0,
                dimension_names=("patch", "channel", "y", "x"))
        else:
            arr = group.create_array(name, shape=data.shape, dtype="int32", chunks=data.shape,
                                     compressors=_compressor(), fill_value=0)
        arr[...] = data
    group.attrs["checksums"] = {name: _array_digest(directory / name) for name in arrays}


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


def write_scene(path: str | os.PathLike, split: str, scene_id: str, arrays: dict[str, np.ndarray],
                scene_attrs: dict) -> None:
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
    attrs = _jsonable({
        **scene_attrs, "scene_id": scene_id, "has_specular": "noisy_specular" in data,
        "n_rows": len(data["spp"]), "n_crops": len(data["origin"]),
        "spp_levels": sorted({int(s) for s in data["spp"]}),
    }, f"{where}: scene_attrs")

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


def has_scene(path: str | os.PathLike, split: str, scene_id: str) -> bool:
    """True when the scene is published (complete: only whole scenes are ever renamed into place)."""
    _check_split(split)
    _check_name(scene_id, "scene_id")
    return (Path(path) / split / scene_id / "zarr.json").is_file()


def list_scenes(path: str | os.PathLike, split: str) -> list[str]:
    """Published scenes of a split, sorted."""
    _check_split(split)
    base = Path(path) / split
    if not base.is_dir():
        return []
    return sorted(p.name for p in base.iterdir() if _NAME.fullmatch(p.name) and (p / "zarr.json").is_file())


def discard_staging(path: str | os.PathLike) -> int:
    """Delete what killed writers left in `_staging/`; call only when no writer is running."""
    staging = Path(path) / STAGING
    left = [p for p in staging.iterdir() if p.is_dir()] if staging.is_dir() else []
    for p in left:
        shutil.rmtree(p)
    return len(left)


class PatchReader:
    """Random access to one split's patch rows, as float32 arrays ready for training.

    Row i of the "diffuse" branch pairs noisy_diffuse, features and the row's reference crop;
    the "specular" branch indexes only scenes that have specular arrays. Index arrays are loaded
    once per scene; each item then reads exactly one chunk of each image array. Picklable (for
    DataLoader workers): array handles are reopened lazily in each process.
    """

    def __init__(self, path: str | os.PathLike, split: str, expect_transform: dict | None = None,
                 branch: str = "diffuse"):
        _check_split(split)
        if branch not in BRANCHES:
            raise PatchStoreError(f"branch {branch!r}: must be one of {BRANCHES}")
        self.path = Path(path)
        self.split = split
        self.branch = branch
        root = _open_root(self.path)
        self.attrs = dict(root.attrs)
        if expect_transform is not None:
            want = _jsonable(expect_transform, "expect_transform")
            diff = differing_keys(self.attrs.get("transform"), want)
            if diff:
                have = {"transform": self.attrs.get("transform")}
                raise PatchStoreError(
                    f"{self.path}: transform spec differs from the model's in {', '.join(diff)} "
                    f"(e.g. {diff[0]}: store has {_lookup(have, 'transform.' + diff[0])!r}, "
                    f"model expects {_lookup({'t': want}, 't.' + diff[0])!r})")
        self.scenes: list[str] = []
        self._spp: list[np.ndarray] = []
        self._crop: list[np.ndarray] = []
        self._starts: list[int] = []
        total = 0
        for scene in list_scenes(self.path, split):
            with _reading(self.path, split, scene, "zarr.json"):
                group = root[f"{split}/{scene}"]
                if branch == "specular" and not group.attrs["has_specular"]:
                    continue
            self.scenes.append(scene)
            for name, out in (("spp", self._spp), ("crop", self._crop)):
                with _reading(self.path, split, scene, name):
                    out.append(group[name][...])
            self._starts.append(total)
            total += len(self._spp[-1])
        self._len = total
        self._root: zarr.Group | None = None
        self._arrays: dict[str, zarr.Array] = {}

    def __len__(self) -> int:
        return self._len

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_root": None, "_arrays": {}}

    def _array(self, scene: str, name: str) -> zarr.Array:
        key = f"{self.split}/{scene}/{name}"
        if key not in self._arrays:
            if self._root is None:
                self._root = zarr.open_group(store=LocalStore(self.path, read_only=True), mode="r")
            self._arrays[key] = self._root[key]
        return self._arrays[key]

    def locate(self, i: int) -> tuple[str, int]:
        """(scene, row within the scene) of global row i."""
        k, row = self._locate(i)
        return self.scenes[k], row

    def _locate(self, i: int) -> tuple[int, int]:
        if not -self._len <= i < self._len:
            raise IndexError(f"row {i} out of range for {self._len} rows in {self.path}/{self.split}")
        i %= self._len
        k = bisect.bisect_right(self._starts, i) - 1
        return k, i - self._starts[k]

    def __getitem__(self, i: int) -> dict[str, Any]:
        k, row = self._locate(i)
        scene = self.scenes[k]
        crop = int(self._crop[k][row])
        return {
            "noisy": self._patch(scene, f"noisy_{self.branch}", row),
            "features": self._patch(scene, "features", row),
            "reference": self._patch(scene, f"ref_{self.branch}", crop),
            "spp": int(self._spp[k][row]),
            "scene": scene,
        }

    def _patch(self, scene: str, name: str, index: int) -> np.ndarray:
        with _reading(self.path, self.split, scene, name):
            return self._array(scene, name)[index].astype(np.float32)


def _add_counts(total: dict, counts: Any) -> None:
    """Sum nested {buffer: {kind: count}} dictionaries."""
    for key, value in counts.items():
        if isinstance(value, dict):
            _add_counts(total.setdefault(key, {}), value)
        elif isinstance(value, (int, float)):
            total[key] = total.get(key, 0) + value


def store_summary(path: str | os.PathLike) -> dict:
    """Counts per split, spp level and branch; value ranges per array; sanitisation totals.

    Reads every patch once (for the ranges): meant for reports, not for the training loop.
    """
    path = Path(path)
    root = _open_root(path)
    summary: dict[str, Any] = {"format_version": root.attrs["format_version"], "splits": {},
                               "sanitization": {}, "staging_leftovers": 0}
    staging = path / STAGING
    summary["staging_leftovers"] = sum(1 for p in staging.iterdir() if p.is_dir()) if staging.is_dir() else 0
    for split in SPLITS:
        entry: dict[str, Any] = {"scenes": [], "rows": {b: 0 for b in BRANCHES}, "crops": 0,
                                 "rows_per_spp": {}, "ranges": {}}
        for scene in list_scenes(path, split):
            damaged = damaged_arrays(path, split, scene)
            if damaged:
                raise _damage_error(path, split, scene, damaged, "its files differ from the checksums written with it")
            group = root[f"{split}/{scene}"]
            entry["scenes"].append(scene)
            n = int(group.attrs["n_rows"])
            entry["rows"]["diffuse"] += n
            entry["rows"]["specular"] += n if group.attrs["has_specular"] else 0
            entry["crops"] += int(group.attrs["n_crops"])
            for spp, count in zip(*np.unique(group["spp"][...], return_counts=True)):
                entry["rows_per_spp"][int(spp)] = entry["rows_per_spp"].get(int(spp), 0) + int(count)
            for name in (*ROW_IMAGES, *CROP_IMAGES):
                if name in group:
                    with _reading(path, split, scene, name):
                        values = group[name][...]
                    lo, hi = float(values.min()), float(values.max())
                    old = entry["ranges"].get(name, (lo, hi))
                    entry["ranges"][name] = (min(old[0], lo), max(old[1], hi))
            _add_counts(summary["sanitization"], dict(group.attrs["sanitization"]))
        summary["splits"][split] = entry
    return summary
