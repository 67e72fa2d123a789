"""What the stages share: the task cache of a config, one run of the corpus's tasks that links the finished
renders and then reports every failure together, and the split of the corpus's scenes."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from admc.errors import StageError
from admc.pipeline.config import Config
from admc.pipeline.engine import runner, slurm
from admc.pipeline.engine.cache import Task, TaskCache, TaskError
from admc.pipeline.render import backends as render
from admc.pipeline.render.scenes import NotAScene, SceneError, SceneSpec
from admc.pipeline.tiler import tile
from admc.stores.atomic import read_json

CACHED_STAGES = ("render", "tile")
"""The stages whose tasks the cache holds: render.render_tasks' and build_dataset's."""


def check_cached_stage(stage: str | None) -> None:
    """Refuse a stage name the cache never holds (`cache --stage renders` would match nothing, silently)."""
    if stage is not None and stage not in CACHED_STAGES:
        raise StageError(f"--stage {stage!r}: not a cached stage; the stages are {', '.join(CACHED_STAGES)}")


def corpus_splits(cfg: Config, specs: list[SceneSpec]) -> dict[str, str]:
    """{scene id: split} by tile.split, tile.seed and tile.split_exact: the one rule that tiling, training's
    checks and evaluation read, so the test frames evaluation scores are never frames that trained."""
    return tile.assign_splits([s.scene_id for s in specs], cfg.tile.split, cfg.tile.seed, cfg.tile.split_exact)


def open_cache(cfg: Config) -> TaskCache:
    """The task cache under run.workdir, as an absolute path: dask workers started in other folders
    must write where this process reads."""
    return TaskCache((Path(cfg.run.workdir) / "cache").resolve())


@dataclass
class StageResult:
    scenes: list[SceneSpec]
    sidecars: list[dict]  # one per render, in corpus order
    tiles: list[dict]  # one per scene (empty for render-only runs)
    renders_dir: Path
    store: Path | None
    executed: int
    cached: int
    tasks: list[Task]  # every task of the run, upstream included (for their manifests)
    retiled: list[str] = field(default_factory=list)  # damaged scenes tiled again ("split/scene (arrays)")
    skipped: list[str] = field(default_factory=list)  # files in the scene folders that are no scene, and why

    @property
    def notes(self) -> list[str]:
        """What the user should hear about besides the counts."""
        retiled = (
            [f"re-tiled damaged scenes from their cached renders: {', '.join(self.retiled)}"] if self.retiled else []
        )
        return self.skipped + retiled


def run_cached(cfg: Config, tasks: list[Task], progress: bool) -> tuple[dict[str, Path], int]:
    """Run tasks (and what they depend on) through the task cache; return published paths and how many were cached."""
    store = open_cache(cfg)
    cached = sum(store.is_done(t) for t in runner.collect(tasks).values())
    logs = cfg.workdir_path("slurm-logs").resolve()  # the jobs' logs, on the shared file system
    with slurm.scheduler_address(cfg.run.scheduler, cfg.cluster, logs) as scheduler:
        published = runner.run(tasks, store, scheduler=scheduler, workers=cfg.run.workers or None, progress=progress)
    return published, cached


def read_sidecars(renders: dict[str, dict[str, Task]], published: dict[str, Path]) -> list[dict]:
    return [read_json(published[t.key] / render.SIDECAR_NAME) for levels in renders.values() for t in levels.values()]


def run_corpus(
    cfg: Config, tasks: list[Task], renders: dict[str, dict[str, Task]], left_out: list[SceneError], progress: bool
) -> tuple[dict[str, Path], int, Path]:
    """Run the corpus's tasks and link every fully rendered scene under workdir/renders; then fail
    naming each failed task and each scene file left out, so the good scenes' work is done first."""
    cache = open_cache(cfg)
    try:
        published, cached = run_cached(cfg, tasks, progress)
        failure = None
    except TaskError as error:
        published, cached, failure = {}, 0, error
    done = {scene_id: levels for scene_id, levels in renders.items() if all(map(cache.is_done, levels.values()))}
    paths = {task.key: cache.path(task) for levels in done.values() for task in levels.values()}
    renders_dir = render.link_renders(done, paths, Path(cfg.run.workdir) / "renders")
    broken = [error for error in left_out if not isinstance(error, NotAScene)]
    if failure is None and not broken:
        return published, cached, renders_dir
    report = [str(failure)] if failure is not None else []
    if broken:
        report += [
            f"{len(broken)} scene file(s) left out of the corpus (fix and rerun: only what is missing runs):",
            *(f"  {error}" for error in broken),
        ]
    report += [str(error) for error in left_out if isinstance(error, NotAScene)]
    raise StageError("\n".join(report)) from failure


def skipped_files(left_out: list[SceneError]) -> list[str]:
    return [str(error) for error in left_out if isinstance(error, NotAScene)]
