"""`admc-pipe dataset`: the corpus rendered and tiled into the patch store, as one task graph."""

from __future__ import annotations

from pathlib import Path

import admc
from admc.common import buffers, oidn
from admc.errors import ConfigError, StageError
from admc.model import transforms
from admc.model.inference import oidn_base
from admc.model.nets.settings import DOWNSAMPLING
from admc.pipeline.config import Config
from admc.pipeline.tiler import tile
from admc.pipeline.engine import runner
from admc.pipeline.engine.cache import Task, code_version
from admc.pipeline.render import backends as render
from admc.pipeline.render.scenes import SceneError, SceneSpec
from admc.pipeline.stages.corpus import (
    StageResult,
    corpus_splits,
    open_cache,
    read_sidecars,
    run_corpus,
    skipped_files,
)
from admc.stores import patches

TILE_CODE = code_version(tile, buffers, transforms, oidn_base, oidn, patches)


def store_attributes(cfg: Config) -> dict:
    """What every scene of one store must share: a corpus never mixes transforms or render settings."""
    return {
        "transform": transforms.transform_spec(),
        "patch_size": cfg.tile.patch_size,
        "render": {
            "spp": list(cfg.render.spp),
            "reference_spp": cfg.render.reference_spp,
            "max_depth": cfg.render.max_depth,
        },
        "tile": {
            "crops_per_scene": cfg.tile.crops_per_scene,
            "candidates_per_crop": cfg.tile.candidates_per_crop,
            "split": list(cfg.tile.split),
            **({"split_exact": True} if cfg.tile.split_exact else {}),
            "seed": cfg.tile.seed,
            **({"clean_targets": True} if cfg.tile.clean_targets else {}),
        },
        "feature_channels": list(transforms.FEATURE_CHANNELS),
        "admc_version": admc.__version__,
    }


def dataset_splits(cfg: Config, left_out: list[SceneError] | None = None) -> dict[str, tuple[SceneSpec, str]]:
    """{scene id: (spec, split)} of what the patch store holds: the corpus split by tile.split, except
    that with tile.val_set = "ood" the val split is the out-of-family set (checkpoints are then selected
    on scenes unlike the training ones) and the corpus's own val scenes are left out."""
    specs = render.corpus(cfg, left_out)
    splits = corpus_splits(cfg, specs)
    chosen = {spec.scene_id: (spec, splits[spec.scene_id]) for spec in specs}
    if cfg.tile.val_set == "ood":
        chosen = {key: value for key, value in chosen.items() if value[1] != "val"}
        chosen.update({spec.scene_id: (spec, "val") for spec in render.ood_corpus(cfg)})
    return chosen


def val_scenes(splits: dict[str, tuple[SceneSpec, str]]) -> frozenset[str]:
    """The scenes the store validates on: their references are rendered at render.val_reference_spp."""
    return frozenset(scene_id for scene_id, (_, split) in splits.items() if split == "val")


def _check_store_matches(store: Path, splits: dict[str, tuple[SceneSpec, str]], cfg: Config) -> None:
    """Every scene the store holds must sit where the config now puts it. A scene tiled into one split and now
    assigned another (tile.split_exact recomputes the cuts from the whole corpus, so adding frames can move
    one) would train on frames it validates or tests on; a val split mixing corpus and out-of-family scenes
    (tile.val_set changed) would select on neither."""
    for split in patches.SPLITS:
        stored = patches.list_scenes(store, split)
        for scene_id in stored:
            now = splits.get(scene_id, (None, split))[1]
            if now != split:
                raise StageError(
                    f"{store}: holds {scene_id} in its {split} split, and tile.split now puts it in {now} "
                    "(with tile.split_exact the corpus's size sets the cuts); tile into a new store: "
                    "--set tile.store=<new name> (the renders are cached)"
                )
        if split != "val":
            continue
        strays = sorted(scene_id for scene_id in stored if scene_id not in splits)
        if strays:
            raise StageError(
                f"{store}: its val split holds {strays[0]} (and {len(strays) - 1} more), which "
                f"tile.val_set = {cfg.tile.val_set!r} does not put there; use another tile.store"
            )


def build_dataset(cfg: Config, progress: bool = True, render_missing: bool = True) -> StageResult:
    """Render + tile as one graph: each scene's tile task depends on its render tasks (failures: see render_corpus)."""
    left_out: list[SceneError] = []
    splits = dataset_splits(cfg, left_out)
    specs = [spec for spec, _ in splits.values()]
    check_patch_fits(cfg, specs)
    renders = render.render_tasks(cfg, specs, val_scenes(splits))
    store_path = cfg.workdir_path(cfg.tile.store).resolve()
    patches.create_store(store_path, store_attributes(cfg))
    _check_store_matches(store_path, splits, cfg)
    cache = open_cache(cfg)
    if not render_missing:
        missing = [t.label for levels in renders.values() for t in levels.values() if not cache.is_done(t)]
        if missing:
            raise StageError(
                f"{len(missing)} renders are missing (e.g. {missing[0]}): run `admc-pipe render` "
                "or `admc-pipe dataset` first"
            )
    tiles, retiled = [], []
    for spec in specs:
        levels = renders[spec.scene_id]
        split = splits[spec.scene_id][1]
        task = Task(
            stage="tile",
            label=f"tile {spec.scene_id}",
            fn=tile.tile_scene,
            inputs=levels,
            code_version=TILE_CODE,
            params={
                "store": str(store_path),
                "split": split,
                "scene_id": spec.scene_id,
                "scene_hash": levels["reference"].params["scene_hash"],
                "patch_size": cfg.tile.patch_size,
                "crops_per_scene": cfg.tile.crops_per_scene,
                "candidates_per_crop": cfg.tile.candidates_per_crop,
                "seed": cfg.tile.seed,
                "refiner_base": cfg.tile.refiner_base if cfg.tile.oidn_base else None,
                **({"noise_maps": True} if noise_maps(cfg) else {}),
                # val keeps the raw reference: OIDN's output on it shares OIDN's errors, so it would favour
                # OIDN (and the blend toward it) where a truer reference does not
                **({"clean_targets": True} if cfg.tile.clean_targets and split == "train" else {}),
            },
            source=render.scene_source(spec),
        )
        if cache.is_done(task) and not _scene_intact(store_path, split, spec.scene_id, retiled, noise_maps(cfg)):
            cache.forget(task)  # the store lost or damaged this scene: tile it again from the cached renders
        tiles.append(task)
    published, cached, renders_dir = run_corpus(cfg, tiles, renders, left_out, progress)
    summaries = [cache.summary(t) for t in tiles]
    everything = list(runner.collect(tiles).values())
    return StageResult(
        specs,
        read_sidecars(renders, published),
        summaries,
        renders_dir,
        store_path,
        len(everything) - cached,
        cached,
        everything,
        retiled,
        skipped_files(left_out),
    )


def noise_maps(cfg: Config) -> bool:
    """Whether tiling stores the noise maps: tile.noise_maps, or a model.noise_input that trains on them."""
    return cfg.tile.noise_maps or cfg.model.noise_input


def _scene_intact(store: Path, split: str, scene_id: str, damaged: list[str], noise: bool = False) -> bool:
    """Whether a tiled scene is published and its files match their checksums; damaged ones are
    described in `damaged` ("split/scene (arrays)") so the user learns what was repaired. With `noise`,
    a scene tiled since without noise maps (by a run without them, into the same store) is not."""
    if not patches.has_scene(store, split, scene_id):
        return False
    if noise and not patches.has_noise_maps(store, split, scene_id):
        return False
    arrays = patches.damaged_arrays(store, split, scene_id)
    if arrays:
        damaged.append(f"{split}/{scene_id} ({', '.join(arrays)})")
    return not arrays


def check_patch_fits(cfg: Config, specs: list[SceneSpec]) -> None:
    """Refuse a tile.patch_size larger than a scene's image before anything is rendered or created."""
    patch = cfg.tile.patch_size
    for spec in specs:
        width, height = spec.resolution
        if patch <= min(width, height):
            continue
        largest = min(width, height) // DOWNSAMPLING * DOWNSAMPLING
        fix = [f"use at most {largest}"] if largest else []
        if spec.is_xml and cfg.corpus.xml_resolution == "film":
            source = f"scene {spec.xml_path} renders at its film's {width}x{height} (corpus.xml_resolution = film)"
            fix.append("set corpus.xml_resolution = render")
        else:
            source = f"render.resolution is {width}x{height}"
            fix.append("raise render.resolution")
        raise ConfigError(
            f"config key 'tile.patch_size': {patch} is larger than the image, {source}; {' or '.join(fix)}"
        )


def existing_dataset(cfg: Config) -> StageResult:
    """The store as it is, without rendering or tiling anything."""
    store_path = cfg.workdir_path(cfg.tile.store).resolve()
    if not patches.exists(store_path):
        raise StageError(f"no patch store at {store_path}: run `admc-pipe dataset` first")
    return StageResult([], [], [], Path(cfg.run.workdir) / "renders", store_path, 0, 0, [])
