"""Scene files as people publish them: the camera and lights in a shared <include>, `$spp` and
`$resx`/`$resy` taken from `mitsuba -D`, and a scene without any light. Tiny real scenes, rendered
for real (32x32, 4 spp), through the library and the CLI as a user runs it."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from admc.pipeline.render.scenes import NotAScene, SceneError, load_scene, scene_hash, xml_corpus
from admc.stores.exr import read_exr

ADMC = str(Path(sys.executable).parent / "admc-pipe")

COMMON = """<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="4"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="45"/>
        <transform name="to_world"><lookat origin="0, 2, 4" target="0, 0.3, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$resx"/><integer name="height" value="$resy"/>
            <rfilter type="gaussian"/>
        </film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="0.8"/></emitter>
</scene>
"""


def setup_file(shape: str) -> str:
    """One object setup, published as its own file; the camera and lights come from the shared include."""
    return f"""<scene version="3.0.0">
    <default name="spp" value="64"/><default name="resx" value="64"/><default name="resy" value="48"/>
    <include filename="common.xml"/>
    {shape}
    <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform>
        <bsdf type="diffuse"/></shape>
</scene>
"""


SHAPES = {
    "sphere": '<shape type="sphere"><point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.5"/>'
    '<bsdf type="roughplastic"/></shape>',
    "cube": '<shape type="cube"><transform name="to_world"><scale value="0.4"/><translate y="0.4"/></transform>'
    '<bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.6, 0.3"/></bsdf></shape>',
    "disk": '<shape type="disk"><transform name="to_world"><translate y="0.3"/></transform>'
    '<bsdf type="conductor"/></shape>',
}
UNLIT = COMMON.replace('<emitter type="constant"><rgb name="radiance" value="0.8"/></emitter>', SHAPES["cube"])
"""A whole scene, camera included, with no light at all."""


def published_folder(folder: Path) -> Path:
    """The layout of a published scene set: one file per object setup, camera and lights shared."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "common.xml").write_text(COMMON)
    for name, shape in SHAPES.items():
        (folder / f"{name}.xml").write_text(setup_file(shape))
    return folder


def test_scenes_whose_camera_comes_from_an_include_are_scenes_and_the_include_is_named(tmp_path, variant):
    folder = published_folder(tmp_path / "published")
    (folder / "materials.xml").write_text('<scene version="3.0.0"><bsdf type="diffuse" id="white"/></scene>')
    (folder / "notes.xml").write_text("<notes>rendered with mitsuba -D spp=1024</notes>")
    left_out: list[SceneError] = []
    specs = xml_corpus([str(folder)], (32, 32), left_out)
    assert [spec.scene_id for spec in specs] == ["xml-cube", "xml-disk", "xml-sphere"]
    assert all(isinstance(error, NotAScene) for error in left_out)
    assert sorted(map(str, left_out)) == [
        f"{folder / 'common.xml'}: skipped, a part of other scenes, not a scene of its own "
        "(included by cube.xml, disk.xml, sphere.xml)",
        f"{folder / 'materials.xml'}: skipped, no <sensor> (camera) in it or in the files it includes",
        f"{folder / 'notes.xml'}: skipped, not a Mitsuba scene (its root element is <notes>)",
    ]
    sphere = next(spec for spec in specs if spec.scene_id == "xml-sphere")
    scene = load_scene(sphere, spp=4)
    film = scene.sensors()[0].film()  # the included sensor got our film, not the scene's Gaussian one
    assert film.rfilter().class_name() == "BoxFilter" and list(film.size()) == [32, 32]
    assert scene.sensors()[0].sampler().sample_count() == 4  # $spp is the spp rendered, not the <default>
    import mitsuba as mi

    image = np.array(mi.render(scene, spp=4, seed=0))
    assert np.isfinite(image).all() and image.mean() > 0.05  # lit by the included emitter
    before = scene_hash(sphere)
    (folder / "common.xml").write_text(COMMON.replace('value="0.8"', 'value="0.5"'))
    assert scene_hash(sphere) != before  # an edited include is a changed scene: rendered again


def test_a_scene_taking_spp_and_film_size_parameters_without_defaults_loads_with_the_render_s(tmp_path, variant):
    folder = tmp_path / "scenes"
    folder.mkdir()
    scene_file = folder / "bare.xml"
    scene_file.write_text(COMMON.replace('<emitter type="constant">', SHAPES["cube"] + '<emitter type="constant">'))
    (spec,) = xml_corpus([str(folder)], (32, 24))
    loaded = load_scene(spec, spp=4)
    assert loaded.sensors()[0].sampler().sample_count() == 4 and list(loaded.sensors()[0].film().size()) == [32, 24]
    with pytest.raises(SceneError, match=r"bare\.xml: \$resx is used but has no <default>"):
        xml_corpus([str(folder)], None)  # the scene's own film size is asked for, and it names none


def test_an_undefined_parameter_is_named_with_its_file(tmp_path):
    folder = published_folder(tmp_path / "published")
    (folder / "glass.xml").write_text(
        setup_file(
            SHAPES["sphere"].replace(
                '<bsdf type="roughplastic"/>', '<bsdf type="dielectric"><float name="int_ior" value="$ior"/></bsdf>'
            )
        )
    )
    left_out: list[SceneError] = []
    specs = xml_corpus([str(folder)], (32, 32), left_out)
    assert "xml-glass" not in [spec.scene_id for spec in specs] and len(specs) == 3
    (error,) = [error for error in left_out if not isinstance(error, NotAScene)]
    assert str(error) == (
        f"{folder / 'glass.xml'}: $ior is used but has no <default> "
        "(admc passes only $spp, $resx, $resy, as `mitsuba -D` would)"
    )


def test_a_scene_without_any_emitter_is_refused_by_name(tmp_path):
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "unlit.xml").write_text(UNLIT)
    with pytest.raises(
        SceneError,
        match=r"unlit\.xml: no <emitter> \(no light, no environment\) in it or in the "
        r"files it includes: it would render black",
    ):
        xml_corpus([str(folder)], (32, 32))
    area = SHAPES["cube"].replace("</shape>", '<emitter type="area"><rgb name="radiance" value="5"/></emitter></shape>')
    (folder / "unlit.xml").write_text(UNLIT.replace("</scene>", area + "</scene>"))
    assert len(xml_corpus([str(folder)], (32, 32))) == 1  # an area light is an emitter too


def test_the_cli_renders_a_published_folder_and_names_every_file_it_left_out(tmp_path, variant):
    """As a user runs it: the included scenes render (non-black), the shared include and the unlit scene
    are named, one line each; the unlit one is a user error (exit 2) after the others are rendered."""
    folder = published_folder(tmp_path / "published")
    unlit = folder / "unlit.xml"
    unlit.write_text(UNLIT)
    work = tmp_path / "work"
    flags = [
        "--set",
        f"run.workdir='{work}'",
        "--set",
        "run.scheduler=sync",
        "--set",
        "render.resolution=[32, 32]",
        "--set",
        "render.spp=[4]",
        "--set",
        "render.reference_spp=8",
        "--set",
        "corpus.n_scenes=0",
        "--set",
        f"corpus.xml_dirs=['{folder}']",
    ]
    wide = dict(os.environ, COLUMNS="1000")  # one line per file, however long its path
    out = subprocess.run([ADMC, "render", *flags], capture_output=True, text=True, timeout=600, env=wide)
    assert out.returncode == 2, out.stdout + out.stderr
    assert "Traceback" not in out.stderr
    assert f"{unlit}: no <emitter> (no light, no environment)" in out.stderr
    assert f"{folder / 'common.xml'}: skipped, a part of other scenes" in out.stderr
    for name in SHAPES:  # the good scenes were rendered all the same
        layers = read_exr(work / "renders" / f"xml-{name}" / "spp0004.exr")
        assert (layers["diffuse"] + layers.get("specular", 0.0)).mean() > 0.05, name
    unlit.unlink()
    out = subprocess.run([ADMC, "render", *flags], capture_output=True, text=True, timeout=600, env=wide)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"{folder / 'common.xml'}: skipped, a part of other scenes, not a scene of its own" in out.stdout
    assert "0 rendered now, 6 cached" in out.stdout


def test_includes_that_form_a_cycle_are_named(tmp_path):
    (tmp_path / "a.xml").write_text(
        '<scene version="3.0.0"><include filename="b.xml"/><sensor type="perspective"/>'
        '<emitter type="constant"/></scene>'
    )
    (tmp_path / "b.xml").write_text('<scene version="3.0.0"><include filename="a.xml"/></scene>')
    left_out: list[SceneError] = []
    assert xml_corpus([str(tmp_path)], (32, 32), left_out) == []
    assert list(map(str, left_out)) == [
        f"{tmp_path / 'a.xml'}: its includes form a cycle (a.xml -> b.xml -> a.xml)",
        f"{tmp_path / 'b.xml'}: its includes form a cycle (b.xml -> a.xml -> b.xml)",
    ]
