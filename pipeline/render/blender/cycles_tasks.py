"""`.blend` corpus scenes and their render tasks: the same per-(scene, spp) EXR + JSON sidecar as the
Mitsuba path (`pipeline/render/tasks.py`), through the same task cache, so tiling, training and
evaluation take them as they take Mitsuba renders.

A task runs Blender once (`worker.py` in its own process, see `locate.py`): it opens the .blend, renders
`render.cycles_subrenders` independent sub-renders with seeds of their own, and this side combines them
(`passes.py`) and writes the admc EXR. A killed task leaves only its temporary folder behind, so a rerun
renders what is missing and nothing else, like a Mitsuba render.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

import admc.pipeline.render.blender as package
from admc.common import buffers, camera
from admc.errors import AdmcError
from admc.pipeline.engine.cache import Task, code_version
from admc.stores import exr, exr_parts

from . import passes
from .locate import SETUP_HINT, BlenderMissing, require_blender

BLEND_FAMILY = "blend"
WORKER = Path(__file__).with_name("worker.py")
EXR_NAME = "render.exr"  # as pipeline/render/tasks.py names them: tiling and linking read these
SIDECAR_NAME = "render.json"
BLEND_CODE = code_version(package, buffers, camera, exr, exr_parts)
BLENDER_TIMEOUT_S = 24 * 3600


class BlendSceneError(AdmcError, ValueError):
    """A .blend scene cannot be used or failed to render; the message names the file."""


@dataclass(frozen=True)
class BlendSpec:
    """A .blend corpus scene: what SceneSpec is for Mitsuba scenes (scene_id, family, seed, resolution)."""

    scene_id: str
    blend_path: str
    resolution: tuple[int, int]
    family: str = BLEND_FAMILY
    seed: int = 0
    constructs: tuple[str, ...] = ()
    xml_path: None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution", tuple(int(v) for v in self.resolution))

    @property
    def is_xml(self) -> bool:
        return False


def is_blend(spec) -> bool:
    return isinstance(spec, BlendSpec)


def blend_corpus(dirs: list[str], resolution: tuple[int, int] | None, blender: str = "") -> list[BlendSpec]:
    """One scene per `*.blend` in each folder and its direct subfolders (Blender's `.blend1` backups are not
    scenes); resolution None: each file's own output size (asks Blender once for all of them)."""
    files: dict[str, Path] = {}
    for folder in map(Path, dirs):
        if not folder.is_dir():
            raise BlendSceneError(f"{folder}: scene folder not found (corpus.blend_dirs)")
        found = sorted([*folder.glob("*.blend"), *folder.glob("*/*.blend")])
        if not found:
            raise BlendSceneError(f"{folder}: no .blend file in this folder or its subfolders (corpus.blend_dirs)")
        for path in found:
            scene_id = "blend-" + (re.sub(r"[^a-z0-9]+", "-", path.stem.lower()).strip("-") or "scene")
            if scene_id in files:
                raise BlendSceneError(f"{path}: scene id {scene_id!r} is already taken by {files[scene_id]}")
            files[scene_id] = path.resolve()
    if not files:
        return []
    require_blender(blender, f"{next(iter(files.values()))} (corpus.blend_dirs)")
    sizes = {} if resolution is not None else own_resolutions(tuple(map(str, files.values())), blender)
    return [BlendSpec(scene_id, str(path), resolution or sizes[str(path)]) for scene_id, path in files.items()]


@cache
def own_resolutions(paths: tuple[str, ...], blender: str = "") -> dict[str, tuple[int, int]]:
    """Each .blend's output size (resolution x percentage), read by one Blender process."""
    with tempfile.TemporaryDirectory(prefix="admc-blend-") as folder:
        report = run_worker({"info": list(paths), "out_dir": folder}, Path(folder), blender, paths[0])
    return {path: tuple(size) for path, size in report["resolutions"].items()}


def blend_hash(spec: BlendSpec) -> str:
    """sha256 of the .blend's bytes and the film size (images it links from other files are not in it:
    after editing one, `admc-pipe cache --clear --stage render`)."""
    digest = hashlib.sha256(b"admc-blend-scene-v1;")
    digest.update(Path(spec.blend_path).read_bytes())
    digest.update(json.dumps(list(spec.resolution)).encode())
    return digest.hexdigest()


def subrender_plan(spp: int, seed: int, count: int) -> list[tuple[int, int]]:
    """(spp, Cycles seed) of each sub-render: spp split as evenly as possible over min(count, spp)
    sub-renders, seeds hashed from the render's own (not seed + i, which would correlate neighbours)."""
    count = max(1, min(count, spp))
    base, extra = divmod(spp, count)
    seeds = np.random.SeedSequence(seed).generate_state(count, dtype=np.uint32) & 0x7FFFFFFF
    return [(base + (1 if i < extra else 0), int(s)) for i, s in enumerate(seeds)]


def run_worker(job: dict, folder: Path, blender: str, what: str) -> dict:
    """Run worker.py in Blender on `job` (written to folder/job.json); its done.json, or a BlendSceneError."""
    command = require_blender(blender, what)
    job_path = folder / "job.json"
    job_path.write_text(json.dumps(job))
    out = subprocess.run(
        [*command, str(WORKER), "--", str(job_path)],
        capture_output=True,
        text=True,
        timeout=BLENDER_TIMEOUT_S,
        stdin=subprocess.DEVNULL,
    )
    done = folder / "done.json"
    if "No module named 'bpy'" in out.stderr:
        raise BlenderMissing(f"{what}: {command[0]} cannot import bpy; {SETUP_HINT}")
    if out.returncode != 0 or not done.is_file():
        tail = " | ".join((out.stderr.strip() or out.stdout.strip()).splitlines()[-3:])
        raise BlendSceneError(f"{what}: Blender failed (exit {out.returncode}): {tail}")
    report = json.loads(done.read_text())
    if not report.get("ok"):
        raise BlendSceneError(f"{what}: {report.get('error', 'Blender reported no result')}")
    return report


def render_blend(
    out_dir: Path,
    inputs: dict,
    *,
    scene: dict,
    spp: int,
    seed: int,
    reference: bool,
    subrenders: int,
    blender: str,
    threads: int,
) -> dict:
    """Task body: render one (.blend, spp) with Cycles into out_dir/render.exr + render.json."""
    from admc.pipeline.render.tasks import _half_safe  # the Mitsuba path's rule for half EXRs

    spec = BlendSpec(**{**scene, "resolution": tuple(scene["resolution"])})
    if not Path(spec.blend_path).is_file():
        raise BlendSceneError(f"{spec.blend_path}: no such file")
    plan = subrender_plan(spp, seed, subrenders)
    folder = Path(out_dir) / "_subrenders"
    folder.mkdir()
    start = time.perf_counter()
    job = {
        "blend": spec.blend_path,
        "resolution": list(spec.resolution),
        "subrenders": plan,
        "out_dir": str(folder),
        "threads": threads,
    }
    report = run_worker(job, folder, blender, spec.blend_path)
    wall = time.perf_counter() - start
    parts, seconds = [], 0.0
    for index, (sub_spp, _) in enumerate(plan):
        try:
            layers, sub_seconds = passes.read_subrender(folder / f"sub{index:03d}.exr", report["view_layer"])
        except passes.PassError as exc:
            raise BlendSceneError(f"{spec.blend_path}: {exc}") from None
        parts.append((layers, sub_spp))
        seconds += sub_seconds
    layers = passes.combine(parts)
    shutil.rmtree(folder)
    nonfinite = exr.nonfinite_report(layers)
    clamped = 0
    if not reference:
        layers, clamped = _half_safe(layers)
    exr.write_exr(
        Path(out_dir) / EXR_NAME,
        layers,
        precision="float" if reference else "half",
        attributes={"admc_scene": spec.scene_id, "admc_spp": str(spp)},
    )
    if seconds <= 0:  # Blender's header counts in 10 ms steps: a tiny render reads 0; take the render calls' wall time
        seconds = sum(report["seconds"])
    seconds = max(seconds, 1e-6)
    sidecar = {
        "scene_id": spec.scene_id,
        "family": spec.family,
        "scene_hash": blend_hash(spec),
        "spp": spp,
        "reference": reference,
        "seed": seed,
        "variant": f"cycles-cpu (Blender {report['blender']})",
        "resolution": list(spec.resolution),
        "render_seconds": round(seconds, 4),
        "warmup_seconds": round(max(wall - seconds, 0.0), 4),
        "samples_per_second": spp * spec.resolution[0] * spec.resolution[1] / seconds,
        "constructs": [],
        "has_specular": True,
        "bsdf_types": [],
        "layers": sorted(layers),
        "nonfinite": nonfinite,
        "fp16_clamped": clamped,
        "blend_file": spec.blend_path,
        "subrenders": [list(p) for p in plan],
        "camera": report["camera"],
        "world_to_camera": report["world_to_camera"],
    }
    (Path(out_dir) / SIDECAR_NAME).write_text(json.dumps(sidecar, indent=2))
    return sidecar


def blend_render_tasks(cfg, specs: list[BlendSpec]) -> dict[str, dict[str, Task]]:
    """Per scene: {"spp0004": task, ..., "reference": task}, as render_tasks gives for Mitsuba scenes."""
    from admc.pipeline.render.tasks import level_label, render_levels

    tasks: dict[str, dict[str, Task]] = {}
    for spec in specs:
        tasks[spec.scene_id] = {}
        for name, key in render_levels(cfg, spec, blend_hash(spec)):
            params = {
                **key,
                "subrenders": cfg.render.cycles_subrenders,
                "blender": cfg.render.blender,
                "threads": cfg.render.blender_threads,
            }
            tasks[spec.scene_id][name] = Task(
                stage="render",
                label=level_label(spec.scene_id, params) + " (Cycles)",
                fn=_blend_task,
                params=params,
                code_version=BLEND_CODE,
                source=spec.blend_path,
            )
    return tasks


def _blend_task(out_dir: Path, inputs: dict, *, scene_hash: str, **params) -> dict:
    """The cached task: scene_hash is only part of the key (a changed .blend means a new render)."""
    return render_blend(out_dir, inputs, **params)
