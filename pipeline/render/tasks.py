"""The render stage: one cached task per (scene, spp) writes a multi-layer EXR and a JSON sidecar.

Noisy inputs are stored in half precision (what the patch store keeps anyway), references in
float32. Each (scene, spp) gets its own seed derived from the base seed, so the noise of the inputs
and the reference is independent. The scene is analysed first: a scene with no glossy, conductor or
dielectric BSDF renders no specular buffer at all.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

from admc.common import buffers
from admc.common.layout import FP16_MAX
from admc.pipeline.config import Config
from admc.pipeline.engine.cache import Task, code_version
from admc.pipeline.render import integrator, scenes
from admc.pipeline.render.scenes import SceneSpec
from admc.pipeline.render.variants import use_variant
from admc.stores import exr

EXR_NAME = "render.exr"
SIDECAR_NAME = "render.json"
RENDER_CODE = code_version(integrator, scenes, buffers, exr, sys.modules[__name__])


def derive_seed(base_seed: int, scene_id: str, spp: int, reference: bool) -> int:
    """A 31-bit seed, independent per (scene, spp, role), identical on every machine."""
    text = f"{base_seed}/{scene_id}/{spp}/{'ref' if reference else 'noisy'}"
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little") & 0x7FFFFFFF


def _half_safe(layers: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int]:
    """Clamp finite values beyond the FP16 range so a half EXR never invents inf; count them."""
    clamped, out = 0, {}
    for name, arr in layers.items():
        finite = np.isfinite(arr)
        over = finite & (np.abs(arr) > FP16_MAX)
        clamped += int(over.sum())
        out[name] = np.where(over, np.sign(arr) * FP16_MAX, arr).astype(np.float32)
    return out, clamped


def view_space_normals(normal: np.ndarray, scene) -> np.ndarray:
    """World-space normals to the camera's view space: x right, y up, z toward the viewer.

    Why: in view space an image flip or transpose is a sign flip or swap of normal components, so
    training can augment patches consistently; world-space normals have no relation to image axes.
    Mitsuba's camera frame is x left, y up, z forward; a 180-degree turn about y gives ours.
    """
    to_world = np.array(scene.sensors()[0].world_transform().matrix, dtype=np.float64).reshape(4, 4)[:3, :3]
    rotation = to_world / np.linalg.norm(to_world, axis=0, keepdims=True)
    camera = normal.astype(np.float64) @ rotation
    return (camera * np.array([-1.0, 1.0, -1.0])).astype(np.float32)


def render_one(
    out_dir: Path,
    inputs: dict,
    *,
    scene: dict,
    spp: int,
    seed: int,
    reference: bool,
    variant: str,
    max_depth: int,
    max_spp_per_pass: int,
) -> dict:
    """Task body: render one (scene, spp) into out_dir/render.exr + render.json."""
    spec = SceneSpec(**{**scene, "resolution": tuple(scene["resolution"])})
    active = use_variant(variant)
    integrator.register()
    loaded = scenes.load_scene(spec, spp)
    needs = scenes.analyse(loaded)
    start = time.perf_counter()
    # A 1-spp warm-up compiles the JIT kernels, so render_seconds measures sampling alone: the
    # error-against-time curves compare spp levels, and compile time would dominate low spp.
    integrator.render_buffers(loaded, 1, seed ^ 0x2545F491, split=needs.has_specular, max_depth=max_depth)
    compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    layers = integrator.render_buffers(
        loaded, spp, seed, split=needs.has_specular, max_depth=max_depth, max_spp_per_pass=max_spp_per_pass
    )
    seconds = time.perf_counter() - start
    layers["normal"] = view_space_normals(layers["normal"], loaded)
    nonfinite = exr.nonfinite_report(layers)
    clamped = 0
    if not reference:
        layers, clamped = _half_safe(layers)
    exr.write_exr(
        out_dir / EXR_NAME,
        layers,
        precision="float" if reference else "half",
        attributes={"admc_scene": spec.scene_id, "admc_spp": str(spp)},
    )
    sidecar = {
        "scene_id": spec.scene_id,
        "family": spec.family,
        "scene_hash": scenes.scene_hash(spec),
        "spp": spp,
        "reference": reference,
        "seed": seed,
        "variant": active,
        "resolution": list(spec.resolution),
        "render_seconds": round(seconds, 4),
        "warmup_seconds": round(compile_seconds, 4),
        "samples_per_second": spp * spec.resolution[0] * spec.resolution[1] / max(seconds, 1e-9),
        "constructs": list(spec.constructs),
        "has_specular": needs.has_specular,
        "bsdf_types": list(needs.bsdf_types),
        "layers": sorted(layers),
        "nonfinite": nonfinite,
        "fp16_clamped": clamped,
    }
    (out_dir / SIDECAR_NAME).write_text(json.dumps(sidecar, indent=2))
    return sidecar


def corpus(cfg: Config, left_out: list[scenes.SceneError] | None = None) -> list[SceneSpec]:
    """Procedural scenes, then the user's XML scenes (a broken one raises, or goes to `left_out`: see xml_corpus)."""
    specs = scenes.procedural_corpus(
        list(cfg.corpus.families),
        cfg.corpus.n_scenes,
        cfg.corpus.seed,
        cfg.render.resolution,
        cfg.corpus.constructs,
        cfg.corpus.construct_chance,
    )
    if cfg.corpus.xml_dirs:
        own_film = cfg.corpus.xml_resolution == "film"
        specs += scenes.xml_corpus(list(cfg.corpus.xml_dirs), None if own_film else cfg.render.resolution, left_out)
    return specs


def ood_corpus(cfg: Config) -> list[SceneSpec]:
    """The out-of-family set: `eval.ood_scenes_per_family` scenes of each of `eval.ood_families` (held out
    of training), drawn with `eval.ood_seed`, plain (no training constructs mixed in)."""
    families = list(cfg.eval.ood_families)
    return scenes.procedural_corpus(
        families, cfg.eval.ood_scenes_per_family * len(families), cfg.eval.ood_seed, cfg.render.resolution
    )


def render_levels(cfg: Config, spec, content: str) -> list[tuple[str, dict]]:
    """(name, key params) of every render one scene gets, whichever renderer makes it: its noisy inputs at
    render.spp ("spp0004", ...) and its "reference", each from a seed of its own."""
    levels = [(f"spp{s:04d}", s, False) for s in cfg.render.spp]
    levels.append(("reference", cfg.render.reference_spp, True))
    return [
        (
            name,
            {
                "scene": dataclasses.asdict(spec),
                "scene_hash": content,
                "spp": spp,
                "reference": reference,
                "seed": derive_seed(cfg.render.seed, spec.scene_id, spp, reference),
            },
        )
        for name, spp, reference in levels
    ]


def level_label(scene_id: str, params: dict) -> str:
    """How progress names one render: "room-0001 @ 16 spp", "room-0001 @ reference 384 spp"."""
    return f"{scene_id} @ {'reference ' if params['reference'] else ''}{params['spp']} spp"


def render_tasks(cfg: Config, specs: list[SceneSpec]) -> dict[str, dict[str, Task]]:
    """Per scene: {"spp0004": task, ..., "reference": task}; keyed by the scene's content hash."""
    variant = use_variant(cfg.render.variant)  # resolved here: "auto" must not hide which variant rendered
    tasks: dict[str, dict[str, Task]] = {}
    for spec in specs:
        tasks[spec.scene_id] = {}
        for name, key in render_levels(cfg, spec, scenes.scene_hash(spec)):
            params = {
                **key,
                "variant": variant,
                "max_depth": cfg.render.max_depth,
                "max_spp_per_pass": cfg.render.max_spp_per_pass,
            }
            tasks[spec.scene_id][name] = Task(
                stage="render",
                label=level_label(spec.scene_id, params),
                fn=_render_task,
                params=params,
                code_version=RENDER_CODE,
                source=scene_source(spec),
            )
    return tasks


def scene_source(spec: SceneSpec) -> str:
    """What a user calls the scene: its XML file, or the procedural scene's id."""
    return spec.xml_path or spec.scene_id


def _render_task(out_dir: Path, inputs: dict, *, scene_hash: str, **params) -> dict:
    """The cached task: scene_hash is only part of the key (a changed XML file means a new render)."""
    return render_one(out_dir, inputs, **params)


def link_renders(tasks: dict[str, dict[str, Task]], published: dict[str, Path], dest: Path) -> Path:
    """A readable view of the cache: dest/<scene_id>/spp0004.exr, .../reference.exr (symlinks)."""
    for scene_id, levels in tasks.items():
        folder = dest / scene_id
        folder.mkdir(parents=True, exist_ok=True)
        for name, task in levels.items():
            for suffix, source in ((".exr", EXR_NAME), (".json", SIDECAR_NAME)):
                link = folder / (name + suffix)
                if link.is_symlink() or link.exists():
                    link.unlink()
                link.symlink_to((published[task.key] / source).resolve())
    return dest
