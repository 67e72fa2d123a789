"""The Zarr v3 patch store: FP16 128x128 training patches, one group per scene, lock-free writers.

format.py holds the constants, opening, listing and checksums; writer.py creates stores and writes
scenes; reader.py reads rows and summarises. This package names their public API.

Layout (LocalStore directory):

    root/                      attrs: format, format_version, patch_size, transform, layout, caller's keys
      _staging/                scenes being written (and replaced scenes being deleted); never read
      train/ val/ test/        one group per split
        <scene_id>/            one group per scene, written by one task; attrs: scene_id, scene_hash,
                               has_specular, has_base, [base], image_size, sanitization, n_rows,
                               n_crops (= n_rows),
                               checksums (sha256 of each array's files, as written)
          noisy_diffuse  (n, 3, P, P) f16   one row per (image crop, spp)
          noisy_specular (n, 3, P, P) f16   only for scenes with specular
          features       (n, 7, P, P) f16   rendered at the row's spp, so per row
          spp            (n,)  int32
          crop           (n,)  int32        row -> its reference entry; the tile stage writes the identity
          ref_diffuse    (n, 3, P, P) f16   one per row: demodulated by that row's own albedo
          ref_specular   (n, 3, P, P) f16   only with specular
          origin         (n, 2) int32       the row's (y, x) in the image
          base_diffuse   (n, 3, P, P) f16   optional (tile.oidn_base): OIDN's output for the row, in the
          base_specular  (n, 3, P, P) f16   noisy arrays' transforms; attr `base` says what made them

Why this shape: a scene group is written whole by one task, so parallel writers never share a
chunk, shard or metadata file (no locks), and adding a scene adds a group without rewriting
anything. The scene list is therefore not kept in the root attributes (that would be a
read-modify-write by every writer); it is the split group's directory listing. A scene is staged
under `_staging/` and renamed into its split last, so a killed writer never leaves a half scene
visible. Each row has its own reference entry: the reference diffuse is divided by the row's own
(noisy) albedo, the albedo inference has, so it cannot be shared between the spp levels of an image
crop. The reader still goes through the `crop` index (tiny, read once per scene); the tile stage
writes it as the identity, so n_crops equals n_rows (format_version 2; version 1 promised one
shared reference per image crop and is refused). The OIDN bases are optional arrays, not a new
version: a store without them stays valid for model.base = "noisy", and a reader that needs them
names the scene that lacks them.
Image arrays have chunks of exactly one patch (a random read decodes one patch) grouped into
shards of up to SHARD_PATCHES patches (few files per scene). Zarr checksums only a shard's index:
flipped bytes inside a compressed chunk mostly decode to wrong values without any error, so each
scene records a checksum per array and `damaged_arrays` compares them.
"""

from __future__ import annotations

from admc.stores.patches.format import (
    BASE_IMAGES,
    FORMAT,
    FORMAT_VERSION,
    SPLITS,
    STAGING,
    SHARD_PATCHES,
    ROW_IMAGES,
    CROP_IMAGES,
    SPECULAR_ARRAYS,
    REQUIRED_ROOT_ATTRS,
    REQUIRED_SCENE_ATTRS,
    LAYOUT,
    NOISE_IMAGES,
    PatchStoreError,
    exists,
    fingerprint,
    has_noise_maps,
    has_scene,
    list_scenes,
    damaged_arrays,
)
from admc.stores.patches.reader import PatchReader, store_summary
from admc.stores.patches.writer import create_store, discard_staging, write_scene

__all__ = [
    "BASE_IMAGES",
    "CROP_IMAGES",
    "FORMAT",
    "FORMAT_VERSION",
    "LAYOUT",
    "NOISE_IMAGES",
    "PatchReader",
    "PatchStoreError",
    "REQUIRED_ROOT_ATTRS",
    "REQUIRED_SCENE_ATTRS",
    "ROW_IMAGES",
    "SHARD_PATCHES",
    "SPECULAR_ARRAYS",
    "SPLITS",
    "STAGING",
    "create_store",
    "damaged_arrays",
    "discard_staging",
    "exists",
    "fingerprint",
    "has_noise_maps",
    "has_scene",
    "list_scenes",
    "store_summary",
    "write_scene",
]
