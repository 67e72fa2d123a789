"""`admc-pipe render`: every (scene, spp) of the corpus rendered once, through the task cache."""

from __future__ import annotations

from admc.pipeline.config import Config
from admc.pipeline.render import backends as render
from admc.pipeline.render.scenes import SceneError, SceneSpec
from admc.pipeline.stages.corpus import StageResult, read_sidecars, run_corpus, skipped_files


def render_corpus(cfg: Config, progress: bool = True, specs: list[SceneSpec] | None = None) -> StageResult:
    """Render every (scene, spp) of the corpus (or of `specs`) not cached yet; link the EXRs under workdir/renders.

    A broken scene file or a failed render does not stop the others: they finish first, then this raises."""
    left_out: list[SceneError] = []
    specs = render.corpus(cfg, left_out) if specs is None else specs
    renders = render.render_tasks(cfg, specs)
    tasks = [t for levels in renders.values() for t in levels.values()]
    published, cached, renders_dir = run_corpus(cfg, tasks, renders, left_out, progress)
    return StageResult(
        specs,
        read_sidecars(renders, published),
        [],
        renders_dir,
        None,
        len(tasks) - cached,
        cached,
        tasks,
        skipped=skipped_files(left_out),
    )
