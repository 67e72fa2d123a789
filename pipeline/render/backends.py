"""The corpus and its render tasks over both renderers: Mitsuba scenes (procedural families, XML files) through
`tasks.py`, Blender `.blend` scenes through `blender/cycles_tasks.py`. The stages import this module; each renderer's
tasks keep their own code version, so adding Cycles re-rendered no Mitsuba scene.
"""

from __future__ import annotations

from dataclasses import replace

from admc.pipeline.config import Config
from admc.pipeline.engine.cache import Task
from admc.pipeline.render import tasks as mitsuba
from admc.pipeline.render.blender import cycles_tasks as cycles
from admc.pipeline.render.scenes import SceneError

EXR_NAME = mitsuba.EXR_NAME
SIDECAR_NAME = mitsuba.SIDECAR_NAME
link_renders = mitsuba.link_renders
ood_corpus = mitsuba.ood_corpus
assert (cycles.EXR_NAME, cycles.SIDECAR_NAME) == (EXR_NAME, SIDECAR_NAME)


def corpus(cfg: Config, left_out: list[SceneError] | None = None) -> list:
    """Procedural scenes, the user's XML scenes, then the user's .blend scenes."""
    specs = mitsuba.corpus(cfg, left_out)
    if cfg.corpus.blend_dirs:
        own = cfg.corpus.xml_resolution == "film"
        specs += cycles.blend_corpus(
            list(cfg.corpus.blend_dirs), None if own else cfg.render.resolution, cfg.render.blender
        )
    return specs


def render_tasks(cfg: Config, specs: list, val_ids: frozenset[str] = frozenset()) -> dict[str, dict[str, Task]]:
    """Per scene: {"spp0004": task, ..., "reference": task}, in corpus order, whichever renderer renders it.
    `val_ids`: the scenes the store validates on, whose references are rendered at render.val_reference_spp
    where that is set (here, so that the renderers' own code, which keys their caches, stays as it was)."""
    if not (cfg.render.val_reference_spp and val_ids):
        return _render_tasks(cfg, specs)
    val_cfg = replace(cfg, render=replace(cfg.render, reference_spp=cfg.render.val_reference_spp))
    tasks = {
        **_render_tasks(cfg, [spec for spec in specs if spec.scene_id not in val_ids]),
        **_render_tasks(val_cfg, [spec for spec in specs if spec.scene_id in val_ids]),
    }
    return {spec.scene_id: tasks[spec.scene_id] for spec in specs}


def _render_tasks(cfg: Config, specs: list) -> dict[str, dict[str, Task]]:
    blend = [spec for spec in specs if cycles.is_blend(spec)]
    others = [spec for spec in specs if not cycles.is_blend(spec)]
    tasks = {**(mitsuba.render_tasks(cfg, others) if others else {}), **cycles.blend_render_tasks(cfg, blend)}
    return {spec.scene_id: tasks[spec.scene_id] for spec in specs}


def scene_source(spec) -> str:
    """What a user calls the scene: its XML or .blend file, or the procedural scene's id."""
    return spec.blend_path if cycles.is_blend(spec) else mitsuba.scene_source(spec)
