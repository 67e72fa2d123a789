"""Scaling figures: render throughput on a local dask cluster of 1..N worker processes, and the peak
memory of tiling as the corpus grows (tiling streams one scene at a time, so it must stay flat).

Throughput: each worker count gets a fresh workdir and an already started, warmed-up cluster (every
worker has imported Mitsuba and rendered a throwaway corpus, so JIT compilation is not timed); the
clock covers rendering the corpus through the task cache. Tiling memory: the corpus is rendered,
then `admc-pipe tile` (renders nothing, sync scheduler) runs in a child process whose peak RSS is read.

    python benchmarks/bench_cluster.py                                  # 1 and 2 workers, 8 scenes at 64x64
    python benchmarks/bench_cluster.py --workers 1 2 4 --set corpus.n_scenes=32
    python benchmarks/bench_cluster.py --tile-scenes 2 4 8 --skip-throughput
"""

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from admc.pipeline.config import load_config
from admc.pipeline.render.variants import use_variant
from admc.pipeline.stages.render import render_corpus
from admc.stores.patches import store_summary

SMALL = [
    "render.resolution=[64, 64]",
    "render.spp=[4, 16]",
    "render.reference_spp=64",
    "corpus.n_scenes=8",
    "tile.patch_size=32",
]
TILE = ["render.resolution=[128, 128]", "tile.patch_size=64", "tile.crops_per_scene=8"]  # rows worth measuring


def _config(overrides: list[str], workdir: Path, scheduler: str, *extra: str):
    return load_config(None, [*SMALL, *overrides, f"run.workdir='{workdir}'", f"run.scheduler={scheduler}", *extra])


def throughput(overrides: list[str], workers: int, scratch: Path) -> tuple[float, int, int]:
    """Seconds to render the corpus on a warm cluster of `workers` processes, renders and samples done."""
    from distributed import Client, LocalCluster

    with (
        LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.run(use_variant, "auto")
        warm = _config(
            overrides,
            scratch / f"warmup{workers}",
            cluster.scheduler_address,
            f"corpus.n_scenes={workers}",
            "corpus.seed=999",
        )
        render_corpus(warm, progress=False)
        cfg = _config(overrides, scratch / f"workers{workers}", cluster.scheduler_address)
        start = time.perf_counter()
        result = render_corpus(cfg, progress=False)
        wall = time.perf_counter() - start
    samples = sum(s["spp"] * s["resolution"][0] * s["resolution"][1] for s in result.sidecars)
    return wall, len(result.sidecars), samples


def tiling_peak_rss(overrides: list[str], n_scenes: int, scratch: Path) -> tuple[float, int, float]:
    """Peak RSS (MiB) of a child process that tiles an already rendered corpus of n_scenes; patch rows; store MiB."""
    workdir = scratch / f"tile{n_scenes}"
    sets = [*SMALL, *TILE, *overrides, f"run.workdir='{workdir}'", "run.scheduler=sync", f"corpus.n_scenes={n_scenes}"]
    render_corpus(load_config(None, sets), progress=False)
    command = [str(Path(sys.executable).parent / "admc-pipe"), "tile", *[x for s in sets for x in ("--set", s)]]
    log = scratch / f"tile{n_scenes}.log"
    with open(log, "w") as out:
        pid = os.posix_spawn(
            command[0],
            command,
            os.environ,
            file_actions=[(os.POSIX_SPAWN_DUP2, out.fileno(), 1), (os.POSIX_SPAWN_DUP2, out.fileno(), 2)],
        )
    _, status, usage = os.wait4(pid, 0)  # this child's own peak RSS, not the other children's
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"admc-pipe tile failed:\n{log.read_text()}")
    store = workdir / load_config(None, sets).tile.store
    store_mib = sum(p.stat().st_size for p in store.rglob("*") if p.is_file()) / 2**20
    rows = sum(sum(split["rows"].values()) for split in store_summary(store)["splits"].values())
    return usage.ru_maxrss / 1024, rows, store_mib


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", action="append", default=[], dest="overrides", help="section.key=value")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--tile-scenes", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--skip-throughput", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="admc-bench-cluster-") as tmp:
        scratch = Path(tmp)
        if not args.skip_throughput:
            base = None
            for workers in args.workers:
                wall, renders, samples = throughput(args.overrides, workers, scratch)
                base = base or renders / wall
                print(
                    f"{workers} worker(s): {renders} renders in {wall:.1f} s = {renders / wall:.2f} renders/s, "
                    f"{samples / wall / 1e6:.2f} Msamples/s, x{renders / wall / base:.2f} vs {args.workers[0]}"
                )
        for n in args.tile_scenes:
            peak, rows, store_mib = tiling_peak_rss(args.overrides, n, scratch)
            print(f"tiling {n} scenes: peak RSS {peak:.0f} MiB, {rows} patch rows, store {store_mib:.1f} MiB")


if __name__ == "__main__":
    main()
