"""Dataset build figures: render and tile seconds, tiling's share, patches/s, store bytes per patch.

Builds the dataset for the given config (cached tasks are reused, so after `make dataset` this only
reads what the build recorded) and reports from each task's manifest:

    python benchmarks/bench_dataset.py                      # the default corpus in .admc
    python benchmarks/bench_dataset.py --set corpus.n_scenes=4 --set run.workdir="'/tmp/bench'"
"""

import argparse
import time
from pathlib import Path

from admc.pipeline.config import load_config
from admc.pipeline.stages.corpus import open_cache
from admc.pipeline.stages.dataset import build_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path)
    parser.add_argument("--set", action="append", default=[], dest="overrides")
    args = parser.parse_args()
    cfg = load_config(args.config, args.overrides)
    start = time.perf_counter()
    result = build_dataset(cfg, progress=True)
    wall = time.perf_counter() - start
    cache = open_cache(cfg)
    seconds = {"render": 0.0, "tile": 0.0}
    for task in result.tasks:
        seconds[task.stage] += cache.manifest(task)["seconds"]
    render_seconds, tile_seconds = seconds["render"], seconds["tile"]
    sampling = sum(s["render_seconds"] for s in result.sidecars)
    samples = sum(s["spp"] * s["resolution"][0] * s["resolution"][1] for s in result.sidecars)
    rows = sum(t["rows"] for t in result.tiles)
    store_bytes = sum(p.stat().st_size for p in result.store.rglob("*") if p.is_file())
    print(f"scenes: {len(result.scenes)}, renders: {len(result.sidecars)}, patch rows: {rows}")
    print(f"this run: {wall:.1f} s wall ({result.executed} tasks run, {result.cached} cached)")
    print(
        f"render tasks: {render_seconds:.1f} s ({sampling:.1f} s sampling, {samples / sampling / 1e6:.2f} Msamples/s)"
    )
    print(
        f"tile tasks: {tile_seconds:.1f} s, {rows / tile_seconds:.1f} patch rows/s, "
        f"{100 * tile_seconds / (tile_seconds + render_seconds):.1f}% of the build"
    )
    print(f"store: {store_bytes / 2**20:.1f} MiB, {store_bytes / max(rows, 1) / 1024:.1f} KiB per patch row")


if __name__ == "__main__":
    main()
