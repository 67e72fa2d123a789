"""Runs inside Blender: builds seeded procedural .blend scenes, a Cycles domain with no downloaded asset
(geometry from Blender's primitives, textures from its procedural shader nodes).

    python build_scenes.py -- JOB.json      JOB: {"out_dir": folder, "scenes": N, "seed": S, "resolution": [w, h]}

Two families, alternating: `interior`, a closed room (textured floor, painted walls, a ceiling area light,
sometimes a small lamp in view) with furniture and glossy, glass and metal objects; `product`, one object on a
curved studio
backdrop under two or three area lights, in metal, glass, glossy or rough plastic. The same seed writes
the same scenes. Writes out_dir/<family>-<k>.blend and out_dir/done.json: the files written, and each scene's
objects (name, location, material colour), which is what the seed decides (the .blend bytes also hold
pointers and times, which differ from run to run).
"""

import json
import math
import random
import sys

import bpy
from mathutils import Vector


def reset(resolution):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 64
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    scene.world = bpy.data.worlds.new("World")
    scene.world.use_nodes = True
    return scene


def material(name, colour, roughness=0.5, metallic=0.0, transmission=0.0, texture=None, rng=None, emission=0.0):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Transmission Weight"].default_value = transmission
    if emission:
        bsdf.inputs["Emission Color"].default_value = (*colour, 1.0)
        bsdf.inputs["Emission Strength"].default_value = emission
    if texture:
        tex = nodes.new(
            {
                "checker": "ShaderNodeTexChecker",
                "brick": "ShaderNodeTexBrick",
                "noise": "ShaderNodeTexNoise",
                "voronoi": "ShaderNodeTexVoronoi",
            }[texture]
        )
        if "Scale" in tex.inputs:
            tex.inputs["Scale"].default_value = rng.uniform(3.0, 12.0)
        ramp = nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (*[c * 0.35 for c in colour], 1.0)
        ramp.color_ramp.elements[1].color = (*colour, 1.0)
        links.new(tex.outputs[1] if texture in ("checker", "brick") else tex.outputs[0], ramp.inputs["Fac"])
        links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def add(primitive, location, scale, mat, rotation=(0.0, 0.0, 0.0), **kwargs):
    getattr(bpy.ops.mesh, f"primitive_{primitive}_add")(location=location, rotation=rotation, **kwargs)
    obj = bpy.context.active_object
    obj.scale = scale
    obj.data.materials.append(mat)
    if primitive in ("uv_sphere", "torus", "cylinder", "cone", "monkey"):
        bpy.ops.object.shade_smooth()
    return obj


def area_light(location, target, size, power, colour=(1.0, 1.0, 1.0)):
    light = bpy.data.lights.new("Area", "AREA")
    light.size, light.energy, light.color = size, power, colour
    obj = bpy.data.objects.new("Area", light)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = location
    aim(obj, target)
    return obj


def aim(obj, target):
    direction = Vector(target) - Vector(obj.location)
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def camera(location, target, lens):
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    bpy.context.scene.collection.objects.link(cam)
    cam.location = location
    cam.data.lens = lens
    aim(cam, target)
    bpy.context.scene.camera = cam


def random_colour(rng, low=0.15, high=0.85):
    return tuple(rng.uniform(low, high) for _ in range(3))


def special(rng, name):
    """A glossy, glass or metal material (the specular branch's content)."""
    kind = rng.choice(["glossy", "glass", "metal", "rough_metal"])
    if kind == "glass":
        return material(name, (0.95, 0.95, 0.95), roughness=rng.choice([0.0, 0.05]), transmission=1.0)
    if kind.endswith("metal"):
        return material(name, random_colour(rng, 0.5, 0.95), roughness=0.05 if kind == "metal" else 0.35, metallic=1.0)
    return material(name, random_colour(rng), roughness=rng.uniform(0.05, 0.3))


def interior(rng, resolution):
    scene = reset(resolution)
    width, depth, height = rng.uniform(4, 6), rng.uniform(4, 6), rng.uniform(2.6, 3.2)
    floor = material(
        "floor",
        random_colour(rng, 0.3, 0.8),
        roughness=rng.uniform(0.2, 0.7),
        texture=rng.choice(["checker", "brick", "noise"]),
        rng=rng,
    )
    wall = material(
        "wall", random_colour(rng, 0.4, 0.9), roughness=0.8, texture=rng.choice([None, "noise", "voronoi"]), rng=rng
    )
    add("plane", (0, 0, 0), (width / 2, depth / 2, 1), floor)
    add("plane", (0, 0, height), (width / 2, depth / 2, 1), wall, rotation=(math.pi, 0, 0))
    for x, y, rot in (
        (0, depth / 2, (math.pi / 2, 0, 0)),
        (0, -depth / 2, (-math.pi / 2, 0, 0)),
        (width / 2, 0, (0, -math.pi / 2, 0)),
        (-width / 2, 0, (0, math.pi / 2, 0)),
    ):
        add("plane", (x, y, height / 2), (max(width, depth) / 2, max(width, height) / 2, 1), wall, rotation=rot)
    table = material(
        "table",
        random_colour(rng, 0.2, 0.6),
        roughness=rng.uniform(0.1, 0.5),
        texture=rng.choice([None, "noise"]),
        rng=rng,
    )
    tx, ty = rng.uniform(-0.6, 0.6), rng.uniform(0.3, 1.0)
    add("cube", (tx, ty, 0.75), (0.8, 0.5, 0.04), table)
    for dx in (-0.7, 0.7):
        for dy in (-0.4, 0.4):
            add("cube", (tx + dx, ty + dy, 0.37), (0.04, 0.04, 0.37), table)
    for k in range(rng.randint(2, 4)):
        shape = rng.choice(["uv_sphere", "torus", "cylinder", "cone", "monkey"])
        size = rng.uniform(0.12, 0.22)
        add(
            shape,
            (tx + rng.uniform(-0.6, 0.6), ty + rng.uniform(-0.3, 0.3), 0.79 + size),
            (size,) * 3,
            special(rng, f"object{k}"),
            rotation=(0, 0, rng.uniform(0, math.tau)),
        )
    cabinet_x = rng.uniform(-1.5, 1.5)
    add(
        "cube",
        (cabinet_x, depth / 2 - 0.4, 0.45),
        (rng.uniform(0.4, 0.8), 0.3, 0.45),
        material("cabinet", random_colour(rng), roughness=rng.uniform(0.3, 0.8)),
    )
    area_light(
        (0, 0, height - 0.05),
        (0, 0, 0),
        rng.uniform(0.6, 1.2),
        rng.uniform(150, 400),
        colour=(1.0, rng.uniform(0.85, 1.0), rng.uniform(0.7, 0.95)),
    )
    if rng.random() < 0.5:  # a lamp seen directly: a small, bright emitter
        add(
            "uv_sphere",
            (cabinet_x + rng.uniform(-0.2, 0.2), depth / 2 - 0.4, 1.02),
            (0.12,) * 3,
            material("lamp", (1.0, 0.85, 0.6), emission=rng.uniform(5.0, 15.0)),
        )
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.05, 0.06, 0.08, 1)
    camera((rng.uniform(-1.2, 1.2), -depth / 2 + 0.4, rng.uniform(1.3, 1.8)), (tx, ty, 0.8), rng.uniform(20, 28))
    return scene


def product(rng, resolution):
    scene = reset(resolution)
    backdrop = material("backdrop", random_colour(rng, 0.5, 0.95), roughness=rng.uniform(0.4, 0.9))
    add("plane", (0, 0, 0), (6, 6, 1), backdrop)
    add("plane", (0, 3, 3), (6, 3, 1), backdrop, rotation=(math.pi / 2, 0, 0))
    add("cylinder", (0, 2.2, 0.8), (0.8, 0.8, 6), backdrop, rotation=(0, math.pi / 2, 0), vertices=48)
    shape = rng.choice(["monkey", "torus", "uv_sphere", "cylinder", "cone"])
    size = rng.uniform(0.45, 0.7)
    add(shape, (0, 0, size), (size,) * 3, special(rng, "product"), rotation=(0, 0, rng.uniform(-0.8, 0.8)))
    if rng.random() < 0.6:
        add(
            "cube",
            (rng.uniform(0.8, 1.3), rng.uniform(-0.4, 0.4), 0.2),
            (0.2,) * 3,
            material("prop", random_colour(rng), roughness=0.6, texture="checker", rng=rng),
        )
    for k in range(rng.randint(2, 3)):
        angle = rng.uniform(-2.2, 2.2)
        area_light(
            (3.5 * math.sin(angle), -3.5 * math.cos(angle), rng.uniform(1.5, 4.0)),
            (0, 0, size),
            rng.uniform(0.5, 2.0),
            rng.uniform(60, 250),
        )
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.02, 0.02, 0.02, 1)
    camera((rng.uniform(-1.0, 1.0), -4.5, rng.uniform(0.8, 1.8)), (0, 0, size * 0.8), rng.uniform(40, 70))
    return scene


FAMILIES = (("interior", interior), ("product", product))


def main(job_path):
    job = json.loads(open(job_path).read())
    written, contents = [], {}
    for k in range(job["scenes"]):
        name, build = FAMILIES[k % len(FAMILIES)]
        rng = random.Random(f"{job['seed']}/{k}")
        scene = build(rng, job["resolution"])
        path = f"{job['out_dir']}/{name}-{k:03d}.blend"
        bpy.ops.wm.save_as_mainfile(filepath=path, compress=False)
        written.append(path)
        contents[f"{name}-{k:03d}"] = describe(scene)
    with open(f"{job['out_dir']}/done.json", "w") as stream:
        json.dump({"ok": True, "written": written, "scenes": contents}, stream)


def describe(scene):
    """What the seed decided: every object's name, location (mm) and first material's colour."""
    rows = []
    for obj in sorted(scene.objects, key=lambda o: o.name):
        colour = None
        if obj.type == "MESH" and obj.data.materials:
            colour = [
                round(v, 4)
                for v in obj.data.materials[0].node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value
            ]
        rows.append([obj.name, [round(v * 1000) for v in obj.location], colour])
    return rows


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1] if "--" in sys.argv else sys.argv[1])
