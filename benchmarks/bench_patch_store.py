"""Patch store speed: write throughput, bytes on disk per patch row, random single-row read latency.

Synthetic but render-like data (smooth log-radiance plus per-spp noise, blocky features) so that
compression ratios are meaningful; uniform noise would not compress at all.

    .venv/bin/python benchmarks/bench_patch_store.py --rows 512 --scenes 4
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from admc.model.transforms import transform_spec
from admc.stores import patches as P

PATCH = 128
SPP_LEVELS = (1, 4, 16, 64)


def synthetic_scene(seed: int, crops: int, specular: bool) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:PATCH, 0:PATCH] / PATCH
    clean = 2.0 + np.sin(6 * x[None, None] + rng.uniform(0, 6, (crops, 3, 1, 1))) * np.cos(4 * y)

    def noisy(ref: np.ndarray) -> np.ndarray:
        rows = [ref + rng.normal(0, 1.5 / np.sqrt(spp), ref.shape) for spp in SPP_LEVELS]
        return np.clip(np.concatenate(rows), 0, None).astype(np.float16)

    blocks = rng.uniform(0, 1, (crops, 7, 8, 8)).repeat(16, axis=2).repeat(16, axis=3)
    feats = np.concatenate([blocks] * len(SPP_LEVELS)) + rng.normal(0, 0.01, (crops * len(SPP_LEVELS), 7, PATCH, PATCH))
    scene = {
        "noisy_diffuse": noisy(clean),
        "features": np.clip(feats, 0, 1).astype(np.float16),
        "ref_diffuse": clean.astype(np.float16),
        "spp": np.repeat(np.asarray(SPP_LEVELS), crops),
        "crop": np.tile(np.arange(crops), len(SPP_LEVELS)),
        "origin": np.stack([np.arange(crops) * PATCH, np.zeros(crops, int)], axis=1),
    }
    if specular:
        scene["noisy_specular"] = noisy(clean * 0.3)
        scene["ref_specular"] = (clean * 0.3).astype(np.float16)
    return scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, default=512, help="patch rows (one per crop and spp level)")
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--reads", type=int, default=300, help="random single-row reads to time")
    parser.add_argument("--no-specular", action="store_true")
    parser.add_argument("--dir", type=Path, default=None, help="where to put the store (default: a temp dir)")
    args = parser.parse_args()

    crops = max(1, args.rows // (args.scenes * len(SPP_LEVELS)))
    rows = crops * len(SPP_LEVELS) * args.scenes
    specular = not args.no_specular
    base = args.dir or Path(tempfile.mkdtemp(prefix="bench_patches_"))
    path = str(base / "patches.zarr")
    P.create_store(path, {"transform": transform_spec(), "patch_size": PATCH})
    scenes = {f"scene{i:04d}": synthetic_scene(i, crops, specular) for i in range(args.scenes)}
    raw = sum(a.nbytes for scene in scenes.values() for a in scene.values())

    start = time.perf_counter()
    for scene_id, arrays in scenes.items():
        P.write_scene(
            path,
            "train",
            scene_id,
            arrays,
            {"scene_hash": scene_id, "image_size": [crops * PATCH, PATCH], "sanitization": {}},
        )
    write_s = time.perf_counter() - start

    disk = sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())
    reader = P.PatchReader(path, "train", expect_transform=transform_spec(), branch="diffuse")
    reader[0]
    rng = np.random.default_rng(0)
    latencies = []
    for i in rng.integers(0, len(reader), args.reads):
        t = time.perf_counter()
        reader[int(i)]
        latencies.append((time.perf_counter() - t) * 1e3)
    lat = np.asarray(latencies)

    print(f"store: {path}")
    print(f"rows: {rows} ({args.scenes} scenes x {crops} crops x {len(SPP_LEVELS)} spp levels), specular: {specular}")
    print(
        f"write: {write_s:.2f} s, {rows / write_s:.0f} rows/s, {raw / write_s / 1e6:.0f} MB/s of FP16 input "
        "(one writer, fsync included)"
    )
    print(
        f"disk: {disk / 1e6:.1f} MB, {disk / rows / 1e3:.1f} kB per row (FP16 raw {raw / rows / 1e3:.1f} kB, "
        f"ratio {raw / disk:.2f})"
    )
    print(
        f"random row read (noisy + features + reference, {args.reads} reads): median {np.median(lat):.2f} ms, "
        f"p95 {np.percentile(lat, 95):.2f} ms, mean {lat.mean():.2f} ms"
    )


if __name__ == "__main__":
    main()
