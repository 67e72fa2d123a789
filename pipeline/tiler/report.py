"""What a person checks after `make dataset`: counts, value ranges, sanitisation, a contact sheet."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from PIL import Image

from admc.common.layout import ALBEDO, NORMAL
from admc.common.metrics import reinhard, to_ldr
from admc.model import transforms as tf
from admc.stores import patches
from admc.stores.atomic import publishing


def _linear(row: dict, specular: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """Noisy and reference radiance (HWC) of one stored row, through the exact inverse transforms."""
    albedo = row["features"][ALBEDO].transpose(1, 2, 0)
    noisy = tf.diffuse_inverse(row["noisy"].transpose(1, 2, 0), albedo)
    ref = tf.diffuse_inverse(row["reference"].transpose(1, 2, 0), albedo)
    if specular is not None:
        noisy = noisy + tf.specular_inverse(specular["noisy"].transpose(1, 2, 0))
        ref = ref + tf.specular_inverse(specular["reference"].transpose(1, 2, 0))
    return noisy, ref


def contact_sheet_path(workdir: Path, store: Path) -> Path:
    """workdir/contact_sheets/<store name>-<hash of its absolute path>.png: inside the run's workdir, and
    one per store, so two stores side by side (or two of one name) never overwrite each other's sheet."""
    store = Path(store).resolve()
    digest = hashlib.sha256(str(store).encode()).hexdigest()[:8]
    return Path(workdir) / "contact_sheets" / f"{store.name}-{digest}.png"


def contact_sheet(store: Path, out_png: Path, split: str = "train", rows: int = 8, seed: int = 0) -> Path | None:
    """Sample rows of a split as noisy | reference | albedo | normal, one patch per line."""
    diffuse = patches.PatchReader(store, split)
    if len(diffuse) == 0:
        return None
    specular = patches.PatchReader(store, split, branch="specular")
    spec_index = {specular.locate(i): i for i in range(len(specular))}
    picks = np.random.default_rng(seed).choice(len(diffuse), size=min(rows, len(diffuse)), replace=False)
    lines = []
    for i in sorted(picks):
        row = diffuse[i]
        j = spec_index.get(diffuse.locate(i))
        noisy, ref = _linear(row, specular[j] if j is not None else None)
        albedo = (np.clip(row["features"][ALBEDO], 0, 1).transpose(1, 2, 0) * 255).astype(np.uint8)
        normal = (np.clip(row["features"][NORMAL], 0, 1).transpose(1, 2, 0) * 255).astype(np.uint8)
        gap = np.full((noisy.shape[0], 4, 3), 255, np.uint8)
        lines.append(
            np.concatenate([to_ldr(reinhard(noisy)), gap, to_ldr(reinhard(ref)), gap, albedo, gap, normal], axis=1)
        )
        lines.append(np.full((4, lines[-1].shape[1], 3), 255, np.uint8))
    with publishing(out_png) as tmp:
        Image.fromarray(np.concatenate(lines[:-1], axis=0)).save(tmp, format="PNG")
    return out_png
