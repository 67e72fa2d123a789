"""`admc-pipe render`: every (scene, spp) of the corpus rendered once, through the task cache."""

from __future__ import annotations

from admc.pipeline.config import Config
from admc.pipeline.render import backends as render
from admc.pipeline.render.scenes import SceneError, SceneSpec
from admc.pipeline.stages.corpus import StageResult, corpus_splits, read_sidecars, run_corpus, skipped_files


def render_corpus(cfg: Config, progress: bool = True, specs: list[SceneSpec] | None = None) -> StageResult:
    """Render every (scene, spp) of the corpus (or of `specs`) not cached yet; link the EXRs under workdir/renders.
    The corpus's val scenes get the references tiling will use (render.val_reference_spp); `specs` get
    render.reference_spp.

    A broken scene file or a failed render does not stop the others: they finish first, then this raises."""
    left_out: list[SceneError] = []
    val_ids: frozenset[str] = frozenset()
    if specs is None:
        specs = render.corpus(cfg, left_out)
        val_ids = frozenset(scene_id for scene_id, split in corpus_splits(cfg, specs).items() if split == "val")
    renders = render.render_tasks(cfg, specs, val_ids)
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
