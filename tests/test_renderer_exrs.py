"""`denoise` reads what renderers write: Blender Cycles multilayer EXRs (rendered here by Blender), Mitsuba `aov`
outputs (rendered here by Mitsuba), pbrt-v4 gbuffer films (pbrt cannot run in a test: files with the exact
channel names and header attributes its film.cpp and image.cpp write, filled from a Mitsuba render), and any
file through --layers; normals end up in admc's camera frame or the file is refused."""

import json
import subprocess
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from admc.pipeline.render.blender.locate import blender_command
from admc.pipeline.render.tasks import view_space_normals
from admc.pipeline.stages.denoise import DenoiseInputError, load_denoise_input, write_denoised
from admc.pipeline.stages.denoise_formats import LayerMap, LayerMapError
from admc.pipeline.stages.denoise_layers import NormalSpaceError

HERE = Path(__file__).parent
HEADER = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}


def in_blender(script: str, *args: str) -> str:
    command = blender_command()
    if command is None:
        pytest.skip("no Blender (bash scripts/setup.sh --blender installs .venv-blender)")
    out = subprocess.run(
        [*command, str(HERE / "blender" / script), "--", *args], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    return out.stdout


@pytest.fixture(scope="module")
def blender_shot(tmp_path_factory):
    """A real 32x24 Cycles render with light and denoising passes, and its camera's world-to-camera matrix."""
    folder = tmp_path_factory.mktemp("blender")
    stdout = in_blender("render_probe.py", str(folder / "shot.exr"))
    matrix = json.loads(stdout.split("WORLD_TO_CAMERA ")[1].splitlines()[0])
    return folder / "shot.exr", matrix


@pytest.fixture(scope="module")
def mitsuba_aov(tmp_path_factory, variant):
    """A Cornell box rendered by Mitsuba's `aov` integrator as its documentation shows it, written by its film;
    also the world positions and normals, and the camera, to build pbrt-v4 files from."""
    import mitsuba as mi

    folder = tmp_path_factory.mktemp("mitsuba")
    scene_dict = mi.cornell_box()
    scene_dict["sensor"]["film"] = {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}}
    scene_dict["integrator"] = {
        "type": "aov",
        "aovs": "dd.y:depth,nn:sh_normal,albedo:albedo,pos:position",
        "image": {"type": "path"},
    }
    scene = mi.load_dict(scene_dict)
    mi.render(scene, spp=4)
    path = folder / "cbox.exr"
    scene.sensors()[0].film().write(str(path))
    channels = OpenEXR.File(str(path), separate_channels=True).channels()
    world = {
        name: np.stack([channels[f"{name}.{c}"].pixels for c in "XYZ"], -1).astype(np.float32) for name in ("nn", "pos")
    }
    to_world = np.array(scene.sensors()[0].world_transform().matrix, np.float64).reshape(4, 4)
    expected = view_space_normals(world["nn"], scene)  # what admc's own renders hold for these normals
    return path, world, to_world, expected, channels


def test_blender_multilayer_splits_and_brings_normals_into_admcs_camera(blender_shot, tmp_path):
    path, matrix = blender_shot
    loaded = load_denoise_input(path)
    assert loaded.blender_layer == "Shot" and loaded.notes[0] == "shot.exr: read as Blender"
    channels = OpenEXR.File(str(path), separate_channels=True)
    planes = {name: c.pixels for part in channels.parts for name, c in part.channels.items()}
    combined = np.stack([planes[f"Shot.Combined.{c}"] for c in "RGB"], -1)
    diffuse = sum(np.stack([planes[f"Shot.Diffuse {k}.{c}"] for c in "RGB"], -1) for k in ("Direct", "Indirect"))
    diffuse = diffuse * np.stack([planes[f"Shot.Diffuse Color.{c}"] for c in "RGB"], -1)
    np.testing.assert_allclose(loaded.layers["diffuse"], diffuse, rtol=1e-6)
    np.testing.assert_allclose(loaded.layers["diffuse"] + loaded.layers["specular"], combined, rtol=1e-5, atol=1e-6)
    assert loaded.layers["specular"].max() > 0.01  # the glossy sphere
    # The floor's world normal (0, 0, 1) seen by this camera (the bottom rows), in admc's camera frame.
    floor = np.linalg.inv(np.array(matrix).reshape(4, 4)[:3, :3]).T @ [0, 0, 1]
    np.testing.assert_allclose(loaded.layers["normal"][-1, 0], floor / np.linalg.norm(floor), atol=1e-3)
    assert loaded.layers["normal"][..., 2].min() > -0.1  # every normal faces the camera
    hit = loaded.layers["coverage"][..., 0] > 0
    assert 0 < hit.mean() < 1 and (loaded.layers["depth"][~hit] == 0).all()
    assert (loaded.layers["coverage"][loaded.layers["depth"] > 0] == 1).all()

    # Without the Denoising Normal, the world-space Normal pass needs the camera, and then agrees with it.
    without = {k: v for k, v in planes.items() if "Denoising Normal" not in k}
    OpenEXR.File(dict(HEADER), without).write(str(tmp_path / "world.exr"))
    with pytest.raises(
        NormalSpaceError,
        match=r"world\.exr: the normals \(Shot\.Normal\.X.* world space .*"
        r"--world-to-camera .*matrix_world\.inverted",
    ):
        load_denoise_input(tmp_path / "world.exr")
    rotated = load_denoise_input(tmp_path / "world.exr", LayerMap.parse(None, "auto", " ".join(map(str, matrix))))
    inside = hit & np.all(np.linalg.norm(loaded.layers["normal"], axis=-1, keepdims=True) > 0.99, axis=-1)
    np.testing.assert_allclose(rotated.layers["normal"][inside], loaded.layers["normal"][inside], atol=0.05)


def test_blender_output_is_a_layer_blenders_compositor_reads(blender_shot, tmp_path):
    from admc.model.inference.denoiser import DenoiseResult

    path, matrix = blender_shot
    loaded = load_denoise_input(path)
    result = DenoiseResult(
        image=loaded.layers["diffuse"] + loaded.layers["specular"],
        diffuse=loaded.layers["diffuse"],
        specular=loaded.layers["specular"],
        branches=("diffuse", "specular"),
        specular_passed_through=False,
    )
    out = tmp_path / "shot.denoised.exr"
    write_denoised(out, result, source=loaded)
    layout = json.loads(in_blender("read_layout.py", str(out)).split("LAYOUT ")[1].splitlines()[0])
    assert layout["type"] == "MULTILAYER" and layout["layer"] == "Shot"
    assert {"Combined", "Alpha", "admc Diffuse", "admc Specular"} <= set(layout["passes"])


def test_blender_files_of_earlier_versions_and_without_light_passes(blender_shot, tmp_path):
    """Blender 2.8-4.x name the light passes DiffDir, DiffInd, DiffCol in one part; without them Combined is
    denoised as diffuse only; without the denoising data the missing layers are named."""
    path, matrix = blender_shot
    exr = OpenEXR.File(str(path), separate_channels=True)
    planes = {name: c.pixels for part in exr.parts for name, c in part.channels.items()}
    short = {"Diffuse Direct": "DiffDir", "Diffuse Indirect": "DiffInd", "Diffuse Color": "DiffCol"}
    old = {}
    for name, plane in planes.items():
        layer, _, channel = name.rpartition(".")
        view, _, kind = layer.partition(".")
        old[f"RenderLayer.{short.get(kind, kind)}.{channel}"] = plane
    OpenEXR.File(dict(HEADER), dict(old)).write(str(tmp_path / "old.exr"))
    mapping = LayerMap()
    before, after = load_denoise_input(path, mapping), load_denoise_input(tmp_path / "old.exr", mapping)
    assert after.blender_layer == "RenderLayer"
    for name in ("diffuse", "specular", "normal", "albedo", "depth"):
        np.testing.assert_array_equal(before.layers[name], after.layers[name])

    plain = {k: v for k, v in old.items() if ".Diff" not in k}
    OpenEXR.File(dict(HEADER), dict(plain)).write(str(tmp_path / "plain.exr"))
    loaded = load_denoise_input(tmp_path / "plain.exr", mapping)
    assert "specular" not in loaded.layers and any("no diffuse light passes" in n for n in loaded.notes)
    bare = {k: v for k, v in plain.items() if "Denoising" not in k}
    OpenEXR.File(dict(HEADER), dict(bare)).write(str(tmp_path / "bare.exr"))
    with pytest.raises(DenoiseInputError, match=r"bare\.exr: read as Blender, lacks albedo needed .*Denoising Data"):
        load_denoise_input(tmp_path / "bare.exr", mapping)


def test_mitsuba_aov_output_needs_the_sensor_then_matches_admcs_own_normals(mitsuba_aov):
    path, world, to_world, expected, _ = mitsuba_aov
    with pytest.raises(NormalSpaceError, match=r"cbox\.exr: the normals \(nn\.X, nn\.Y, nn\.Z\) are in world space"):
        load_denoise_input(path)
    loaded = load_denoise_input(path, LayerMap.parse(None, "auto", " ".join(map(str, np.linalg.inv(to_world).ravel()))))
    assert loaded.notes[0] == "cbox.exr: read as Mitsuba aov"
    np.testing.assert_allclose(loaded.layers["normal"], expected, atol=1e-5)
    assert set(loaded.layers) == {"diffuse", "albedo", "normal", "depth", "coverage"}
    hit = loaded.layers["coverage"] > 0
    assert hit.mean() > 0.9 and (loaded.layers["depth"][hit] > 0).all()  # the box fills most of the image


def pbrt_file(path, channels, world, to_world, system: str, old_names: bool = False):
    """A gbuffer film's EXR as pbrt-v4 writes it (film.cpp GBufferFilm::GetImage, image.cpp's header)."""
    camera_from_world = np.diag([-1.0, 1.0, 1.0, 1.0]) @ np.linalg.inv(to_world)  # pbrt: x right, z forward
    position, normal = world["pos"], world["nn"]
    if system == "camera":
        position = position @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        normal = normal @ camera_from_world[:3, :3].T
    rgb = {c: channels[c].pixels for c in "RGB"}
    names = (
        {"P": ("Px", "Py", "Pz"), "N": ("Nx", "Ny", "Nz"), "Ns": ("Nsx", "Nsy", "Nsz")}
        if old_names
        else {k: tuple(f"{k}.{c}" for c in "XYZ") for k in ("P", "N", "Ns")}
    )
    planes = {
        **rgb,
        **{f"Albedo.{c}": channels[f"albedo.{c}"].pixels for c in "RGB"},
        **{f"Variance.{c}": np.full_like(rgb["R"], 0.5) for c in "RGB"},
        **{f"RelativeVariance.{c}": np.zeros_like(rgb["R"]) for c in "RGB"},
        "dzdx": np.zeros_like(rgb["R"]),
        "dzdy": np.zeros_like(rgb["R"]),
        "u": rgb["R"] * 0,
        "v": rgb["R"] * 0,
    }
    for key, array in (("P", position), ("N", normal), ("Ns", normal)):
        planes.update({name: np.ascontiguousarray(array[..., i], np.float32) for i, name in enumerate(names[key])})
    header = dict(HEADER, worldToCamera=camera_from_world.astype(np.float32), samplesPerPixel=16, renderTimeSeconds=0.5)
    OpenEXR.File(header, planes).write(str(path))
    return camera_from_world


@pytest.mark.parametrize("system, old_names", [("camera", False), ("world", False), ("camera", True)])
def test_pbrt_gbuffer_in_either_coordinate_system(mitsuba_aov, tmp_path, system, old_names):
    path, world, to_world, expected, channels = mitsuba_aov
    camera_from_world = pbrt_file(tmp_path / "pbrt.exr", channels, world, to_world, system, old_names)
    loaded = load_denoise_input(tmp_path / "pbrt.exr")
    assert loaded.notes[0] == "pbrt.exr: read as pbrt-v4 gbuffer"
    assert any(f"are in {system} space" in n for n in loaded.notes), loaded.notes
    np.testing.assert_allclose(loaded.layers["normal"], expected, atol=1e-4)
    eye, hit = np.linalg.inv(camera_from_world)[:3, 3], np.linalg.norm(world["nn"], axis=-1) > 0
    assert 0.9 < hit.mean() < 1 and (loaded.layers["coverage"][..., 0] == hit).all()
    distance = np.linalg.norm(world["pos"] - eye, axis=-1)
    np.testing.assert_allclose(loaded.layers["depth"][hit, 0], distance[hit], rtol=1e-4)
    assert (loaded.layers["depth"][~hit] == 0).all()
    np.testing.assert_allclose(loaded.layers["diffuse_var"], 0.5 / 16)  # the sample variance over samplesPerPixel


def test_layers_mapping_for_any_other_file(mitsuba_aov, tmp_path):
    path, world, to_world, expected, channels = mitsuba_aov
    planes = {f"beauty.{c}": channels[c].pixels for c in "RGB"}
    planes.update({f"alb.{c}": channels[f"albedo.{c}"].pixels for c in "RGB"})
    planes.update({f"N.{c}": np.ascontiguousarray(expected[..., i]) for i, c in enumerate("XYZ")})
    OpenEXR.File(dict(HEADER), planes).write(str(tmp_path / "frame.exr"))
    with pytest.raises(DenoiseInputError, match=r"frame\.exr: read as EXR with --layers, lacks albedo needed"):
        load_denoise_input(tmp_path / "frame.exr", LayerMap.parse(["colour=beauty", "normal=N"]))
    toml = tmp_path / "layers.toml"
    toml.write_text(
        'normal_space = "camera"\n[layers]\ncolour = "beauty"\nalbedo = ["alb.R", "alb.G", "alb.B"]\nnormal = "N"\n'
    )
    loaded = load_denoise_input(tmp_path / "frame.exr", LayerMap.parse([str(toml)]))
    np.testing.assert_array_equal(loaded.layers["normal"], expected)
    with pytest.raises(LayerMapError, match=r"--layers maps albedo to nothing, which the file does not hold"):
        load_denoise_input(tmp_path / "frame.exr", LayerMap.parse(["colour=beauty", "albedo=nothing", "normal=N"]))
    with pytest.raises(LayerMapError, match=r"--layers: unknown key 'albedos'"):
        LayerMap.parse(["albedos=alb"])
    # world-space normals without a camera in a mapped file: detected and refused, naming how to declare them (the
    # Cornell box's camera looks down the world's -z, so its world is turned 120 degrees about y first)
    turn = np.array([[-0.5, 0, 0.866], [0, 1, 0], [-0.866, 0, -0.5]], np.float32)
    planes.update({f"N.{c}": np.ascontiguousarray((world["nn"] @ turn.T)[..., i]) for i, c in enumerate("XYZ")})
    OpenEXR.File(dict(HEADER), planes).write(str(tmp_path / "world.exr"))
    with pytest.raises(
        NormalSpaceError,
        match=r"world\.exr: the normals \(N\.X, N\.Y, N\.Z\) face away from the camera"
        r" on \d+% .* --normal-space world --world-to-camera",
    ):
        load_denoise_input(tmp_path / "world.exr", LayerMap.parse(["colour=beauty", "albedo=alb", "normal=N"]))


def test_admc_pipe_denoise_on_a_blender_render_and_a_refused_mitsuba_one(blender_shot, mitsuba_aov, tmp_path):
    from test_cli import run

    path, _ = blender_shot
    out = run("denoise", str(path), "-o", str(tmp_path / "shot.denoised.exr"))
    assert out.returncode == 0, out.stderr
    assert "read as Blender" in out.stdout and "normals (Shot.Denoising Normal.X" in out.stdout
    written = OpenEXR.File(str(tmp_path / "shot.denoised.exr"), separate_channels=True).channels()
    assert {f"Shot.{p}.{c}" for p in ("Combined", "admc Diffuse", "admc Specular") for c in "RGB"} <= set(written)
    assert np.isfinite(written["Shot.Combined.R"].pixels).all()
    out = run("denoise", str(mitsuba_aov[0]), "-o", str(tmp_path / "cbox.denoised.exr"))
    assert out.returncode == 2 and "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert "cbox.exr: the normals (nn.X, nn.Y, nn.Z) are in world space" in out.stderr
    out = run("denoise", str(mitsuba_aov[0]), "--layers", "albedos=x")
    assert out.returncode == 2 and "--layers: unknown key 'albedos'" in out.stderr and "Traceback" not in out.stderr
