"""Run inside Blender (a Python with bpy): a 32x24 Cycles render of a sphere on a floor, written as
Blender writes a multilayer EXR with the light and denoising-data passes on. Prints the camera's
world-to-camera matrix as JSON. Usage: python render_probe.py OUT.exr [--no-light-passes]"""

import json
import sys

import bpy

out = sys.argv[sys.argv.index("--") + 1] if "--" in sys.argv else sys.argv[1]
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = 4
scene.cycles.use_denoising = False
scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 32, 24, 100
camera = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
scene.collection.objects.link(camera)
scene.camera = camera
camera.location, camera.rotation_euler = (0.5, -4.0, 1.6), (1.25, 0.0, 0.15)
bpy.ops.mesh.primitive_plane_add(size=20)
bpy.ops.mesh.primitive_uv_sphere_add(location=(0, 0, 1))
glossy = bpy.data.materials.new("glossy")
glossy.use_nodes = True
glossy.node_tree.nodes["Principled BSDF"].inputs["Roughness"].default_value = 0.2
bpy.context.active_object.data.materials.append(glossy)
lamp = bpy.data.objects.new("Lamp", bpy.data.lights.new("Lamp", "POINT"))
lamp.data.energy = 800
lamp.location = (2, -2, 4)
scene.collection.objects.link(lamp)
scene.world = bpy.data.worlds.new("World")
layer = scene.view_layers[0]
layer.name = "Shot"
if "--no-light-passes" not in sys.argv:
    for name in (
        "diffuse_direct",
        "diffuse_indirect",
        "diffuse_color",
        "glossy_direct",
        "glossy_indirect",
        "glossy_color",
        "emit",
        "environment",
    ):
        setattr(layer, f"use_pass_{name}", True)
layer.use_pass_normal = True  # world space, unlike the Denoising Normal
layer.cycles.denoising_store_passes = True
settings = scene.render.image_settings
settings.media_type = "MULTI_LAYER_IMAGE"
settings.file_format = "OPEN_EXR_MULTILAYER"
settings.color_depth = "32"
scene.render.filepath = out
bpy.ops.render.render(write_still=True)
print("WORLD_TO_CAMERA " + json.dumps([v for row in camera.matrix_world.inverted() for v in row]))
