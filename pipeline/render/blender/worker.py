"""Runs inside Blender (a Python with bpy, or `blender -b -P`): renders one .blend scene with Cycles into
multilayer EXRs, one per sub-render, with the passes admc needs. Imports nothing of admc (Blender's
Python has its own NumPy); the job comes as a JSON file, the results are files plus `done.json`.

    python worker.py -- JOB.json        (or: blender -b --factory-startup -P worker.py -- JOB.json)

JOB: {"blend": path, "resolution": [w, h] or null (the file's own), "subrenders": [[spp, seed], ...],
"out_dir": folder, "threads": 0 (all)}. Each sub-render i writes out_dir/sub{i:03d}.exr.
Or {"info": [paths], "out_dir": folder}: each file's output size, {"resolutions": {path: [w, h]}}.

What is forced, whatever the file says, so the passes are what admc's buffers need: Cycles on the CPU,
no adaptive sampling, no denoising, no sample clamping (a clamped reference is biased), a box pixel filter
one pixel wide (a pixel's samples stay its own, as in the Mitsuba renders), no motion blur, an opaque
film (the environment stays in Combined), the compositor and sequencer off (the render result is
written as rendered), and the light and denoising-data passes on in the one view layer rendered. The
scene's own light paths (bounces, caustics), camera, materials and world are kept: the point is to
train on the user's renderer as they set it up.
"""

import json
import sys
import time

import bpy

PASSES = (
    "diffuse_direct",
    "diffuse_indirect",
    "diffuse_color",
    "glossy_direct",
    "glossy_indirect",
    "glossy_color",
    "transmission_direct",
    "transmission_indirect",
    "transmission_color",
    "emit",
    "environment",
)


class JobError(Exception):
    """The .blend cannot be rendered as asked (no camera, unreadable): reported in done.json."""


def configure(scene, resolution, threads: int):
    if scene.camera is None:
        raise JobError("the scene has no active camera")
    scene.render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.use_animated_seed = False
    cycles.sample_clamp_direct = 0.0
    cycles.sample_clamp_indirect = 0.0
    cycles.pixel_filter_type = "BOX"
    cycles.filter_width = 1.0
    render = scene.render
    if resolution is not None:
        render.resolution_x, render.resolution_y = resolution
    render.resolution_percentage = 100
    render.use_border = False
    render.use_motion_blur = False
    render.film_transparent = False
    render.use_compositing = False
    render.use_sequencer = False
    render.threads_mode = "FIXED" if threads else "AUTO"
    if threads:
        render.threads = threads
    layer = bpy.context.view_layer
    for other in scene.view_layers:
        other.use = other == layer
    for name in PASSES:
        setattr(layer, f"use_pass_{name}", True)
    layer.cycles.denoising_store_passes = True
    settings = render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    settings.exr_codec = "ZIP"
    return layer.name


def camera_info(scene):
    camera = scene.camera
    return {
        "camera": camera.name,
        "world_to_camera": [v for row in camera.matrix_world.inverted() for v in row],
        "resolution": [scene.render.resolution_x, scene.render.resolution_y],
    }


def main(job_path: str) -> None:
    job = json.loads(open(job_path).read())
    out_dir = job["out_dir"]
    report = {"ok": False}
    try:
        if "info" in job:
            report = {"ok": True, "resolutions": {path: own_resolution(path) for path in job["info"]}}
            return
        try:
            bpy.ops.wm.open_mainfile(filepath=job["blend"], load_ui=False)
        except RuntimeError as exc:
            raise JobError(f"Blender cannot open it ({str(exc).strip().splitlines()[-1]})") from None
        scene = bpy.context.scene
        view_layer = configure(scene, job["resolution"], job.get("threads", 0))
        seconds = []
        for index, (spp, seed) in enumerate(job["subrenders"]):
            scene.cycles.samples = int(spp)
            scene.cycles.seed = int(seed)
            scene.render.filepath = f"{out_dir}/sub{index:03d}.exr"
            start = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            seconds.append(time.perf_counter() - start)
        report = {
            "ok": True,
            "view_layer": view_layer,
            "seconds": seconds,
            "blender": bpy.app.version_string,
            **camera_info(scene),
        }
    except JobError as exc:
        report = {"ok": False, "error": str(exc)}
    finally:
        with open(f"{out_dir}/done.json", "w") as stream:
            json.dump(report, stream)


def own_resolution(path: str) -> list[int]:
    try:
        bpy.ops.wm.open_mainfile(filepath=path, load_ui=False)
    except RuntimeError as exc:
        raise JobError(f"{path}: Blender cannot open it ({str(exc).strip().splitlines()[-1]})") from None
    render = bpy.context.scene.render
    return [
        max(1, render.resolution_x * render.resolution_percentage // 100),
        max(1, render.resolution_y * render.resolution_percentage // 100),
    ]


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1] if "--" in sys.argv else sys.argv[1])
