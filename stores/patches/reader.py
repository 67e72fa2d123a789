"""Reading the patch store: training rows of a split and branch, and the store's summary."""

from __future__ import annotations

import bisect
import copy
import os
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.storage import LocalStore

from admc.common.diff import differing_keys
from admc.common.layout import BASE_QUALITIES, BRANCHES
from admc.stores.patches.format import (
    BASE_IMAGES,
    CROP_IMAGES,
    NOISE_IMAGES,
    RAW_REF_IMAGES,
    ROW_IMAGES,
    SPLITS,
    STAGING,
    PatchStoreError,
    _check_split,
    _damage_error,
    _jsonable,
    _lookup,
    _open_root,
    _reading,
    damaged_arrays,
    list_scenes,
)


def stored_quality(description: dict, branch: str) -> str | None:
    """A branch's OIDN quality in a scene's record of its bases (oidn_base.describe); scenes tiled before
    the fast bases record one quality for both branches."""
    quality = description.get("quality")
    return quality.get(branch) if isinstance(quality, dict) else quality


class PatchReader:
    """Random access to one split's patch rows, as float32 arrays ready for training.

    Row i of the "diffuse" branch pairs noisy_diffuse, features and the row's reference crop;
    the "specular" branch indexes only scenes that have specular arrays. Index arrays are loaded
    once per scene; each item then reads exactly one chunk of each image array. Picklable (for
    DataLoader workers): array handles are reopened lazily in each process. With `base` (a refining base,
    layout.BASE_QUALITIES), items also carry the row's stored OIDN output ("base"), and every scene must
    have it at the quality that base names for this branch.
    With `noise`, the branch's noise map is appended to "features" as their last channel (what a
    model.noise_input generator reads), and every scene must have it.
    `holds_raw_references`: every scene keeps its raw reference beside a cleaned target (tile.clean_targets);
    a reader from `with_raw_references()` then adds it to each item ("raw_reference").
    """

    def __init__(
        self,
        path: str | os.PathLike,
        split: str,
        expect_transform: dict | None = None,
        branch: str = "diffuse",
        base: str | None = None,
        noise: bool = False,
    ):
        _check_split(split)
        if branch not in BRANCHES:
            raise PatchStoreError(f"branch {branch!r}: must be one of {BRANCHES}")
        self.path = Path(path)
        self.split = split
        self.branch = branch
        self.base = base
        self.noise = noise
        self.raw_references = False
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
                    f"model expects {_lookup({'t': want}, 't.' + diff[0])!r})"
                )
        self.scenes: list[str] = []
        self._spp: list[np.ndarray] = []
        self._crop: list[np.ndarray] = []
        self._starts: list[int] = []
        total = 0
        self.holds_raw_references = True
        for scene in list_scenes(self.path, split):
            with _reading(self.path, split, scene, "zarr.json"):
                group = root[f"{split}/{scene}"]
                if branch == "specular" and not group.attrs["has_specular"]:
                    continue
                has_base = group.attrs.get("has_base", False)
                quality = stored_quality(group.attrs.get("base", {}), branch)
                has_noise = group.attrs.get("has_noise", False)
                self.holds_raw_references &= group.attrs.get("has_raw_references", False)
            if noise and not has_noise:
                raise PatchStoreError(
                    f"patch store {self.path}: scene {split}/{scene} has no noise maps, which model.noise_input = "
                    "true trains on (it was tiled without them); run `admc-pipe dataset` with this config and "
                    "--set model.noise_input=true (or tile.noise_maps=true): it re-tiles from the cached renders"
                )
            if base and not has_base:
                raise PatchStoreError(
                    f"patch store {self.path}: scene {split}/{scene} has no OIDN bases, which model.base {base!r} "
                    "trains on; set tile.oidn_base = true and run `admc-pipe dataset` (it re-tiles from the cached "
                    "renders)"
                )
            if base and quality != BASE_QUALITIES[base][branch]:
                raise PatchStoreError(
                    f"patch store {self.path}: scene {split}/{scene} holds {branch} OIDN bases of quality {quality!r}, "
                    f"model.base {base!r} trains on {BASE_QUALITIES[base][branch]!r} ones; tile with "
                    f"tile.refiner_base = {base!r} into a store of its own (tile.store)"
                )
            self.scenes.append(scene)
            for name, out in (("spp", self._spp), ("crop", self._crop)):
                with _reading(self.path, split, scene, name):
                    out.append(group[name][...])
            self._starts.append(total)
            total += len(self._spp[-1])
        self._len = total
        self.holds_raw_references &= total > 0
        self._root: zarr.Group | None = None
        self._arrays: dict[str, zarr.Array] = {}

    def __len__(self) -> int:
        return self._len

    def with_raw_references(self) -> PatchReader:
        """The same rows, each item with its raw reference too; a store without them is refused."""
        if not self.holds_raw_references:
            raise PatchStoreError(
                f"patch store {self.path}: split {self.split!r} keeps no raw references beside its targets (they are "
                "kept in train scenes tiled with tile.clean_targets = true)"
            )
        other = copy.copy(self)
        other.__dict__.update(self.__getstate__(), raw_references=True)
        return other

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
        item = {
            "noisy": self._patch(scene, f"noisy_{self.branch}", row),
            "features": self._patch(scene, "features", row),
            "reference": self._patch(scene, f"ref_{self.branch}", crop),
            "spp": int(self._spp[k][row]),
            "scene": scene,
        }
        if self.base:
            item["base"] = self._patch(scene, f"base_{self.branch}", row)
        if self.raw_references:
            item["raw_reference"] = self._patch(scene, f"raw_ref_{self.branch}", crop)
        if self.noise:
            item["features"] = np.concatenate([item["features"], self._patch(scene, f"noise_{self.branch}", row)])
        return item

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
    summary: dict[str, Any] = {
        "format_version": root.attrs["format_version"],
        "splits": {},
        "sanitization": {},
        "staging_leftovers": 0,
    }
    staging = path / STAGING
    summary["staging_leftovers"] = sum(1 for p in staging.iterdir() if p.is_dir()) if staging.is_dir() else 0
    for split in SPLITS:
        entry: dict[str, Any] = {
            "scenes": [],
            "rows": {b: 0 for b in BRANCHES},
            "crops": 0,
            "rows_per_spp": {},
            "ranges": {},
        }
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
            for name in (*ROW_IMAGES, *BASE_IMAGES, *NOISE_IMAGES, *CROP_IMAGES, *RAW_REF_IMAGES):
                if name in group:
                    with _reading(path, split, scene, name):
                        values = group[name][...]
                    lo, hi = float(values.min()), float(values.max())
                    old = entry["ranges"].get(name, (lo, hi))
                    entry["ranges"][name] = (min(old[0], lo), max(old[1], hi))
            _add_counts(summary["sanitization"], dict(group.attrs["sanitization"]))
        summary["splits"][split] = entry
    return summary
