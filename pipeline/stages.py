"""The product's stages as functions of a Config: what the CLI and `make` targets call."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from admc.errors import AdmcError
import admc
from admc.model import transforms
from admc.pipeline import render, runner, slurm, tile
from admc.pipeline.cache import StageCache, Task, code_version
from admc.pipeline.config import Config
from admc.pipeline.scenes import SceneSpec
from admc.stores import patches

TILE_CODE = code_version(tile, transforms, patches)


class StageError(AdmcError, RuntimeError):
    """A stage cannot run as asked (e.g. tiling renders that do not exist yet)."""


def open_cache(cfg: Config) -> StageCache:
    """The stage cache under run.workdir, as an absolute path: dask workers started in other folders
    must write where this process reads."""
    return StageCache((Path(cfg.run.workdir) / "cache").resolve())


@dataclass
class StageResult:
    scenes: list[SceneSpec]
    sidecars: list[dict]           # one per render, in corpus order
    tiles: list[dict]              # one per scene (empty for render-only runs)
    renders_dir: Path
    store: Path | None
    executed: int
    cached: int
    tasks: list[Task]              # every task of the run, upstream included (for their manifests)


def run_cached(cfg: Config, tasks: list[Task], progress: bool) -> tuple[dict[str, Path], int]:
    """Run tasks (and what they depend on) through the stage cache; return published paths and how many were cached."""
    store = open_cache(cfg)
    cached = sum(store.is_done(t) for t in runner.collect(tasks).values())
    with slurm.scheduler_address(cfg) as scheduler:
        published = runner.run(tasks, store, scheduler=scheduler, workers=cfg.run.workers or None,
                               progress=progress)
    return published, cached


def _sidecars(renders: dict[str, dict[str, Task]], published: dict[str, Path]) -> list[dict]:
    return [json.loads((published[t.key] / render.SIDECAR_NAME).read_text())
            for levels in renders.values() for t in levels.values()]


def render_corpus(cfg: Config, progress: bool = True, specs: list[SceneSpec] | None = None) -> StageResult:
    """Render every (scene, spp) of the corpus (or of `specs`) not cached yet; link the EXRs under workdir/renders."""
    specs = render.corpus(cfg) if specs is None else specs
    renders = render.render_tasks(cfg, specs)
    tasks = [t for levels in renders.values() for t in levels.values()]
    published, cached = run_cached(cfg, tasks, progress)
    renders_dir = render.link_renders(renders, published, Path(cfg.run.workdir) / "renders")
    return StageResult(specs, _sidecars(renders, published), [], renders_dir, None, len(tasks) - cached, cached,
                       tasks)


def store_attributes(cfg: Config) -> dict:
    """What every scene of one store must share: a corpus never mixes transforms or render settings."""
    return {
        "transform": transforms.transform_spec(),
        "patch_size": cfg.tile.patch_size,
        "render": {"spp": list(cfg.render.spp), "reference_spp": cfg.render.reference_spp,
                   "max_depth": cfg.render.max_depth},
        "tile": {"crops_per_scene": cfg.tile.crops_per_scene, "candidates_per_crop": cfg.tile.candidates_per_crop,
                 "split": list(cfg.tile.split), "seed": cfg.tile.seed},
        "feature_channels": list(transforms.FEATURE_CHANNELS),
        "admc_version": admc.__version__,
    }


def build_dataset(cfg: Config, progress: bool = True, render_missing: bool = True) -> StageResult:
    """Render + tile as one graph: each scene's tile task depends on its render tasks."""
    specs = render.corpus(cfg)
    renders = render.render_tasks(cfg, specs)
    store_path = cfg.workdir_path(cfg.tile.store).resolve()
    patches.create_store(store_path, store_attributes(cfg))
    cache = open_cache(cfg)
    if not render_missing:
        missing = [t.label for levels in renders.values() for t in levels.values() if not cache.is_done(t)]
        if missing:
            raise StageError(f"{len(missing)} renders are missing (e.g. {missing[0]}): run `admc-pipe render` "
                             "or `admc-pipe dataset` first")
    tiles = []
    for spec in specs:
        levels = renders[spec.scene_id]
        split = tile.split_of(spec.scene_id, cfg.tile.split, cfg.tile.seed)
        task = Task(stage="tile", label=f"tile {spec.scene_id}", fn=tile.tile_scene, inputs=levels,
                    code_version=TILE_CODE, params={
                        "store": str(store_path), "split": split, "scene_id": spec.scene_id,
                        "scene_hash": levels["reference"].params["scene_hash"],
                        "patch_size": cfg.tile.patch_size, "crops_per_scene": cfg.tile.crops_per_scene,
                        "candidates_per_crop": cfg.tile.candidates_per_crop, "seed": cfg.tile.seed})
        if cache.is_done(task) and not patches.has_scene(store_path, split, spec.scene_id):
            cache.forget(task)  # the store lost this scene (deleted or moved): tile it again
        tiles.append(task)
    published, cached = run_cached(cfg, tiles, progress)
    renders_dir = render.link_renders(renders, published, Path(cfg.run.workdir) / "renders")
    summaries = [cache.summary(t) for t in tiles]
    everything = list(runner.collect(tiles).values())
    return StageResult(specs, _sidecars(renders, published), summaries, renders_dir, store_path,
                       len(everything) - cached, cached, everything)


def existing_dataset(cfg: Config) -> StageResult:
    """The store as it is, without rendering or tiling anything."""
    store_path = cfg.workdir_path(cfg.tile.store).resolve()
    if not (store_path / "zarr.json").is_file():
        raise StageError(f"no patch store at {store_path}: run `admc-pipe dataset` first")
    return StageResult([], [], [], Path(cfg.run.workdir) / "renders", store_path, 0, 0, [])
