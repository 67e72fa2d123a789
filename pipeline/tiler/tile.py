"""The tile stage: one scene's EXR set (every spp + the reference) -> its group in the patch store.

Crops are chosen once per scene and shared by every spp level, so each noisy row is paired with
the same reference crop. Selection favours informative regions (KPCN-style importance sampling):
candidates are drawn uniformly and kept with probability proportional to their relative noise
plus reference edge strength, with a floor so flat regions still appear. Val scenes are cut on a
grid that covers each frame instead, so validation scores whole frames as the evaluation does.
Splits are assigned per scene by a stable hash, never per patch: by the hash alone a scene never
moves when the corpus grows; tile.split_exact ranks the hashes and cuts them at exact shares instead.
With `refiner_base`, OIDN denoises each whole noisy image per branch (as inference does) at the
qualities of that base and its crops are stored as the rows' bases, the input of an admc+oidn
refiner. With `noise_maps`, each branch's noise map (from the render's variance buffer:
transforms.noise_forward) is stored per row, what model.noise_input reads.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from scipy.ndimage import uniform_filter

from admc.common.buffers import DENOISER_LAYERS, VARIANCE_LAYERS, sanitize
from admc.model import transforms as tf
from admc.model.inference.oidn_base import describe as describe_oidn, oidn_bases
from admc.pipeline.render.tasks import EXR_NAME
from admc.stores import exr, patches

SPLITS = patches.SPLITS
NOISE_FLOOR = 0.1  # share of the mean score every candidate gets, so flat regions are not excluded


def _draw(scene_id: str, seed: int) -> float:
    """The scene's place in [0, 1): a hash of (seed, scene id), the same on every machine."""
    digest = hashlib.sha256(f"{seed}/{scene_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little") / 2**64


def split_of(scene_id: str, fractions: tuple[float, float, float], seed: int) -> str:
    """Stable per-scene split: the scene's hash against the fractions."""
    edges = np.cumsum(fractions) / sum(fractions)
    return SPLITS[int(np.searchsorted(edges, _draw(scene_id, seed), side="right"))]


def assign_splits(
    scene_ids: list[str], fractions: tuple[float, float, float], seed: int, exact: bool = False
) -> dict[str, str]:
    """{scene id: split}. Per scene by hash (split_of) the splits never move as the corpus grows, but a
    small corpus gets its fractions only on average: 20 frames at 60/15/25% can split 14/1/5, one val
    frame to choose every step on. `exact` ranks the same hashes and cuts them at each split's share of
    the corpus (12/3/5): a frame near a cut can move when frames are added or removed."""
    if not exact:
        return {scene_id: split_of(scene_id, fractions, seed) for scene_id in scene_ids}
    ranked = sorted(scene_ids, key=lambda scene_id: (_draw(scene_id, seed), scene_id))
    counts = exact_counts(len(ranked), fractions)
    names = [split for split, count in zip(SPLITS, counts) for _ in range(count)]
    return dict(zip(ranked, names))


def exact_counts(n: int, fractions: tuple[float, float, float]) -> list[int]:
    """Scenes per split for `n` scenes: the fractions' shares rounded by largest remainder, then each
    split with a nonzero fraction given at least one scene (taken from the largest) where n allows."""
    shares = np.asarray(fractions, dtype=np.float64) / sum(fractions) * n
    counts = np.floor(shares).astype(int)
    for i in np.argsort(-(shares - counts), kind="stable")[: n - counts.sum()]:
        counts[i] += 1
    for i in np.flatnonzero((np.asarray(fractions) > 0) & (counts == 0)):
        largest = int(np.argmax(counts))
        if counts[largest] > 1:
            counts[largest] -= 1
            counts[i] += 1
    return counts.tolist()


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def importance_map(noisy: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> np.ndarray:
    """Per-pixel score: relative variance of the noisiest input + relative gradient of the reference."""
    ref = reference["diffuse"] + reference.get("specular", 0.0)
    var = noisy["diffuse_var"] + noisy.get("specular_var", 0.0)
    lum = _luminance(ref)
    rel_var = _luminance(var) / (lum**2 + 1e-2)
    gy, gx = np.gradient(lum)
    rel_grad = np.hypot(gx, gy) / (lum + 1e-2)
    score = np.nan_to_num(rel_var, nan=0.0, posinf=0.0) + np.nan_to_num(rel_grad, nan=0.0, posinf=0.0)
    return np.clip(score, 0.0, 1e6)


def choose_crops(
    score: np.ndarray, n: int, patch: int, candidates_per_crop: int, rng: np.random.Generator
) -> np.ndarray:
    """(n, 2) crop origins (y, x) drawn without replacement from candidates weighted by mean score."""
    h, w = score.shape
    _check_fits(h, w, patch)
    integral = np.pad(score.astype(np.float64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    k = max(n * candidates_per_crop, n)
    ys = rng.integers(0, h - patch + 1, size=k)
    xs = rng.integers(0, w - patch + 1, size=k)
    sums = integral[ys + patch, xs + patch] - integral[ys, xs + patch] - integral[ys + patch, xs] + integral[ys, xs]
    weights = sums / patch**2
    weights = weights + NOISE_FLOOR * (weights.mean() + 1e-12)
    picked = rng.choice(k, size=n, replace=False, p=weights / weights.sum())
    return np.stack([ys[picked], xs[picked]], axis=1).astype(np.int32)


def grid_origins(height: int, width: int, patch: int) -> np.ndarray:
    """(n, 2) crop origins (y, x) that together cover the whole image: ceil(size / patch) crops per axis,
    evenly spaced from edge to edge (overlapping where the size is not a multiple of the patch)."""
    _check_fits(height, width, patch)
    ys, xs = (np.linspace(0, size - patch, -(-size // patch)).round().astype(np.int32) for size in (height, width))
    return np.stack(np.meshgrid(ys, xs, indexing="ij"), axis=-1).reshape(-1, 2)


def _check_fits(height: int, width: int, patch: int) -> None:
    if height < patch or width < patch:
        raise ValueError(f"image {width}x{height} is smaller than the {patch}x{patch} patch size")


def _clean(layers: dict[str, np.ndarray], counts: dict, prefix: str) -> dict[str, np.ndarray]:
    """Sanitize every buffer the store needs; count what was replaced under prefix/<layer>."""
    out = {}
    for name in (*DENOISER_LAYERS, *VARIANCE_LAYERS):
        if name in layers:
            out[name], c = sanitize(layers[name], name)
            if any(c.values()):
                counts[f"{prefix}/{name}"] = c
    return out


def _crops(image: np.ndarray, origins: np.ndarray, patch: int) -> np.ndarray:
    """(H, W, C) -> (n, C, patch, patch)."""
    return np.stack([image[y : y + patch, x : x + patch].transpose(2, 0, 1) for y, x in origins])


def _fp16(name: str, x: np.ndarray, clamped: dict) -> np.ndarray:
    x16, n = tf.to_fp16(x)
    if n:
        clamped[name] = clamped.get(name, 0) + n
    return x16


def _level_images(
    layers: dict[str, np.ndarray],
    ref_diffuse: np.ndarray,
    ref_specular: np.ndarray | None,
    refiner_base: str | None,
    noise_maps: bool = False,
) -> dict[str, np.ndarray]:
    """One spp level's whole images in the store's transforms, (H, W, C) per row array. `ref_diffuse` is
    linear; `ref_specular` is already transformed (it does not depend on the level), None without specular;
    `refiner_base` the refining base whose OIDN bases to add, None for none.

    The reference diffuse is demodulated by this level's own albedo, the one inference has, so
    expm1(output) * (noisy albedo + eps) targets the reference radiance exactly even where a low-spp
    albedo varies (texture detail within a pixel, glass): one reference entry per row.
    """
    albedo = layers["albedo"]
    images = {
        "noisy_diffuse": tf.diffuse_forward(layers["diffuse"], albedo),
        "ref_diffuse": tf.diffuse_forward(ref_diffuse, albedo),
        "features": tf.features(layers["normal"], layers["depth"], albedo, layers["coverage"]),
    }
    if ref_specular is not None:
        images["noisy_specular"] = tf.specular_forward(layers["specular"])
        images["ref_specular"] = ref_specular
    if noise_maps:
        images["noise_diffuse"] = tf.diffuse_noise(layers["diffuse_var"], layers["diffuse"], albedo)
        if ref_specular is not None:
            images["noise_specular"] = tf.specular_noise(layers["specular_var"], layers["specular"])
    if refiner_base is not None:
        bases = oidn_bases(layers, refiner_base)
        images["base_diffuse"] = tf.diffuse_forward(bases["diffuse"], albedo)
        if ref_specular is not None and "specular" in bases:
            images["base_specular"] = tf.specular_forward(bases["specular"])
    return images


UNCONVERGED_REL_STD = (0.2, 0.4)
"""Where a reference's relative standard deviation passes these, its pixels are skewed enough that L1 learns
their median, not their mean: 16 renders at 256 spp of cbox and interior train frames put a pixel's median at
0.94-0.99x its mean between 0.15 and 0.3 and at 0.81-0.97x above 0.3 (caustics seen through glass, light
through a window; docs/results/2026-12-07-val-references.md)."""


def converged_share(reference: dict[str, np.ndarray], branch: str) -> np.ndarray:
    """(H, W, 1) weight of the raw reference in the partner's target: 1 where the reference has converged,
    falling to 0 (the cleaned target) as its relative standard deviation, over 7x7 pixels (one pixel's
    variance is too noisy an estimate of its tail), goes from the first UNCONVERGED_REL_STD to the second."""
    value = uniform_filter(_luminance(reference[branch]), 7)
    var = uniform_filter(_luminance(reference[f"{branch}_var"]), 7)
    rel_std = np.sqrt(np.maximum(var, 0.0)) / np.maximum(value, 1e-3)
    low, high = UNCONVERGED_REL_STD
    return np.clip((high - rel_std) / (high - low), 0.0, 1.0)[..., None].astype(np.float32)


def partner_references(raw: dict[str, np.ndarray], cleaned: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Linear per-branch targets of OIDN's fine-tune on raw references: the raw reference where it has
    converged (it keeps detail OIDN's cleaning blurs), the cleaned one where its noise is heavy-tailed."""
    return {
        branch: (w := converged_share(raw, branch)) * raw[branch] + (1.0 - w) * cleaned[branch]
        for branch in ("diffuse", "specular")
        if branch in raw
    }


def _raw_references(albedo: np.ndarray, diffuse: np.ndarray, specular: np.ndarray | None) -> dict[str, np.ndarray]:
    """The partner's raw-reference target in the store's transforms, as `_level_images` puts a target: beside a
    cleaned one. `diffuse` is linear; `specular` already transformed (it does not depend on the level), None without."""
    images = {"raw_ref_diffuse": tf.diffuse_forward(diffuse, albedo)}
    if specular is not None:
        images["raw_ref_specular"] = specular
    return images


def tile_scene(
    out_dir: Path,
    inputs: dict[str, Path],
    *,
    store: str,
    split: str,
    scene_id: str,
    scene_hash: str,
    patch_size: int,
    crops_per_scene: int,
    candidates_per_crop: int,
    seed: int,
    refiner_base: str | None = None,
    noise_maps: bool = False,
    clean_targets: bool = False,
) -> dict:
    """Task body. inputs: {"reference": render dir, "spp0004": render dir, ...}. `refiner_base`: the
    refining base whose OIDN bases to store (None: none); `clean_targets`: the reference denoised by OIDN
    is what the rows' targets are cut from (tile.clean_targets). Val scenes are cut into crops that cover
    the whole frame (grid_origins) instead of the importance-sampled ones."""

    def read(name: str) -> dict[str, np.ndarray]:
        return exr.read_exr(inputs[name] / EXR_NAME)

    sanitized: dict = {}
    raw_reference = _clean(read("reference"), sanitized, "reference")
    reference = raw_reference
    if clean_targets:  # OIDN's per-branch output on the reference: at a few hundred spp far cleaner than the raw one
        reference = {**raw_reference, **oidn_bases(raw_reference, "oidn")}
    spp_inputs = sorted((k for k in inputs if k != "reference"), key=lambda k: int(k[3:]))
    noisy = {k: _clean(read(k), sanitized, k) for k in spp_inputs}
    has_specular = "specular" in reference
    h, w = reference["diffuse"].shape[:2]

    if split == "val":  # whole frames: what validation scores is then what Table 1 scores on a test frame
        origins = grid_origins(h, w, patch_size)
    else:
        rng = np.random.default_rng([seed, int(scene_hash[:12], 16)])
        score = importance_map(noisy[spp_inputs[0]], reference)
        origins = choose_crops(score, crops_per_scene, patch_size, candidates_per_crop, rng)
    ref_specular = tf.specular_forward(reference["specular"]) if has_specular else None
    partner = partner_references(raw_reference, reference) if clean_targets else {}
    raw_specular = tf.specular_forward(partner["specular"]) if has_specular and clean_targets else None
    rows: dict[str, list] = {}
    for key in spp_inputs:
        images = _level_images(noisy[key], reference["diffuse"], ref_specular, refiner_base, noise_maps)
        if clean_targets:  # the raw reference too: OIDN's fine-tune learns from it (training/oidn_partner.py)
            images |= _raw_references(noisy[key]["albedo"], partner["diffuse"], raw_specular)
        for name, image in images.items():
            rows.setdefault(name, []).append(_crops(image, origins, patch_size))
        rows.setdefault("spp", []).append(np.full(len(origins), int(key[3:]), dtype=np.int32))
        rows.setdefault("origin", []).append(origins)
    clamped: dict = {}
    arrays = {}
    for name, parts in rows.items():
        joined = np.concatenate(parts)
        arrays[name] = joined if name in ("spp", "origin") else _fp16(name, joined, clamped)
    arrays["crop"] = np.arange(len(arrays["spp"]), dtype=np.int32)

    stats = {
        name: {"mean": float(a.astype(np.float32).mean()), "max": float(a.max())}
        for name, a in arrays.items()
        if a.ndim == 4
    }
    patches.write_scene(
        store,
        split,
        scene_id,
        arrays,
        {
            **({"clean_targets": True} if clean_targets else {}),
            "scene_hash": scene_hash,
            "image_size": [w, h],
            "sanitization": sanitized,
            "fp16_clamped": clamped,
            "stats": stats,
            "spp_levels_rendered": [int(k[3:]) for k in spp_inputs],
            "render_keys": {name: Path(path).name for name, path in sorted(inputs.items())},  # the cached renders used
            **({"base": describe_oidn(refiner_base)} if refiner_base is not None else {}),
        },
    )
    return {
        "split": split,
        "scene_id": scene_id,
        "rows": int(len(arrays["spp"])),
        "crops": int(len(origins)),
        "has_specular": has_specular,
        "has_base": refiner_base is not None,
        **({"has_noise": True} if noise_maps else {}),
        "sanitized": sanitized,
        "fp16_clamped": clamped,
    }
