"""The scene corpus: seeded procedural families, the XML loader, hashing and analysis.

Everything renders for real with Mitsuba at 32x32 and 4 spp.
"""

import os
import pickle
import subprocess
import sys

import numpy as np
import pytest

from admc.pipeline.render.scenes import (
    CONSTRUCTS,
    FAMILIES,
    OOD_CONSTRUCTS,
    SceneError,
    SceneSpec,
    analyse,
    load_scene,
    procedural_corpus,
    scene_description,
    scene_hash,
    xml_corpus,
)
from admc.pipeline.render.scenes.meshes import bumpy_sphere, heightfield, lathe
from admc.pipeline.render.scenes.staging import family_rng
from admc.pipeline.scene_names import CONSTRUCT_NAMES, FAMILY_NAMES, OOD_CONSTRUCT_NAMES

RES = (32, 32)


def render(scene, spp=4):
    import mitsuba as mi

    return np.array(mi.render(scene, spp=spp, seed=0))


def luminance(image):
    return image[..., 0] * 0.2126 + image[..., 1] * 0.7152 + image[..., 2] * 0.0722


# ------------------------------------------------------------------------------ procedural


@pytest.mark.parametrize("family", sorted(FAMILIES))
@pytest.mark.parametrize("seed", [1, 3])
def test_same_seed_gives_same_hash_and_bit_identical_render(variant, family, seed):
    first, second = SceneSpec(f"{family}-a", family, seed, RES), SceneSpec(f"{family}-b", family, seed, RES)
    assert scene_hash(first) == scene_hash(second)
    assert np.array_equal(render(load_scene(first)), render(load_scene(second)))


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_different_seeds_give_different_hashes(family):
    hashes = {scene_hash(SceneSpec(f"{family}-{seed}", family, seed, RES)) for seed in range(6)}
    assert len(hashes) == 6
    assert scene_hash(SceneSpec("r", family, 1, RES)) != scene_hash(SceneSpec("r", family, 1, (48, 32)))


def test_hash_does_not_depend_on_the_process():
    """Another interpreter with another str-hash seed computes the same hashes (no set/dict-order leaks)."""
    specs = [SceneSpec(f"{family}-2", family, 2, RES) for family in sorted(FAMILIES)]
    code = (
        "from admc.pipeline.render.scenes import SceneSpec, scene_hash\n"
        f"print(' '.join(scene_hash(SceneSpec(f'{{f}}-2', f, 2, {RES!r})) for f in {sorted(FAMILIES)!r}))"
    )
    env = dict(os.environ, PYTHONHASHSEED="12345")
    other = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert other == [scene_hash(spec) for spec in specs]


@pytest.mark.parametrize("family", sorted(FAMILIES))
@pytest.mark.parametrize("seed", [1, 2, 7])
def test_families_load_with_box_filtered_hdrfilm_and_render_sane_images(variant, family, seed):
    scene = load_scene(SceneSpec(f"{family}-{seed}", family, seed, (40, 24)))
    film = scene.sensors()[0].film()
    assert film.class_name() == "HDRFilm" and film.rfilter().class_name() == "BoxFilter"
    assert list(film.size()) == [40, 24]
    image = render(scene)
    assert image.shape == (24, 40, 3) and np.isfinite(image).all() and (image >= 0).all()
    mean = float(luminance(image).mean())
    assert 0.005 < mean < 5.0, f"{family} seed {seed}: mean luminance {mean}"


def test_room_description_has_everything_the_family_promises(variant):
    import mitsuba as mi

    rooms = [scene_description(SceneSpec(f"room-{seed}", "room", seed, RES)) for seed in range(1, 11)]
    assert all(room["sensor"]["film"]["rfilter"] == {"type": "box"} for room in rooms)
    assert sum(isinstance(value, mi.Mesh) for room in rooms for value in room.values()) >= 10
    assert any("sky" in room for room in rooms) and any("light_point" in room for room in rooms)
    assert all(any(key.startswith("light_panel") for key in room) for room in rooms)


def test_every_fifth_room_is_purely_diffuse_and_the_others_are_not(variant):
    for seed in range(0, 11):
        needs = analyse(load_scene(SceneSpec(f"room-{seed}", "room", seed, RES)))
        assert needs.has_specular == (seed % 5 != 0), (seed, needs)
        if seed % 5 == 0:
            assert set(needs.bsdf_types) <= {"SmoothDiffuse", "TwoSidedBRDF"}


def test_tabletops_always_hold_a_specular_object(variant):
    for seed in range(4):
        assert analyse(load_scene(SceneSpec(f"tabletop-{seed}", "tabletop", seed, RES))).has_specular


def test_the_config_knows_the_families_and_constructs_the_scene_code_builds():
    """pipeline/scene_names.py, what config checks against, lists exactly the registered builders."""
    assert tuple(FAMILIES) == FAMILY_NAMES
    assert tuple(CONSTRUCTS) == CONSTRUCT_NAMES
    assert tuple(OOD_CONSTRUCTS) == OOD_CONSTRUCT_NAMES


def test_procedural_corpus_cycles_families_with_disjoint_seeds():
    corpus = procedural_corpus(["room", "tabletop"], 5, seed=2, resolution=(64, 48))
    assert [spec.scene_id for spec in corpus] == [
        "room-2000000",
        "tabletop-2000000",
        "room-2000001",
        "tabletop-2000001",
        "room-2000002",
    ]
    assert all(spec.resolution == (64, 48) and spec.xml_path is None for spec in corpus)
    assert pickle.loads(pickle.dumps(corpus)) == corpus
    other = procedural_corpus(["room"], 3, seed=3, resolution=(64, 48))
    assert not {spec.seed for spec in corpus} & {spec.seed for spec in other}
    with pytest.raises(SceneError, match="castle"):
        procedural_corpus(["room", "castle"], 2, seed=0, resolution=(64, 48))


def test_procedural_meshes_are_small_with_normals_facing_like_their_triangles():
    rng = family_rng("test", 0)
    meshes = [
        lathe(np.linspace(0.1, 0.2, 20), 0.5, [1.0, 0.0, 2.0]),
        bumpy_sphere(rng, 0.3, [0.0, 1.0, 0.0]),
        heightfield(rng, (2.0, 1.5), 0.05, [0.0, 0.01, 0.0], yaw=30.0),
    ]
    for mesh in meshes:
        assert len(mesh.faces) < 3000 and mesh.faces.max() < len(mesh.vertices)
        a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
        geometric = np.cross(b - a, c - a)
        shading = mesh.normals[mesh.faces].mean(axis=1)
        assert (np.sum(geometric * shading, axis=1) > 0).all()
        assert np.allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-6)


# -------------------------------------------------------------------------------- analysis


def _needs(bsdf):
    import mitsuba as mi

    return analyse(
        mi.load_dict({"type": "scene", "ball": {"type": "sphere", "bsdf": bsdf}, "sky": {"type": "constant"}})
    )


@pytest.mark.parametrize(
    "bsdf, specular",
    [
        ({"type": "diffuse"}, False),
        ({"type": "roughplastic", "alpha": 0.2}, True),
        ({"type": "roughconductor", "alpha": 0.2}, True),
        ({"type": "conductor"}, True),
        ({"type": "conductor", "material": "none"}, True),
        ({"type": "dielectric"}, True),
        ({"type": "thindielectric"}, True),
        ({"type": "twosided", "bsdf": {"type": "diffuse"}}, False),
        ({"type": "twosided", "bsdf": {"type": "roughconductor"}}, True),
        ({"type": "blendbsdf", "weight": 0.3, "bsdf_0": {"type": "diffuse"}, "bsdf_1": {"type": "conductor"}}, True),
        ({"type": "mask", "opacity": 0.5, "bsdf": {"type": "diffuse"}}, False),
    ],
    ids=lambda value: value.get("type") if isinstance(value, dict) else str(value),
)
def test_analyse_finds_glossy_and_delta_lobes_through_nesting(variant, bsdf, specular):
    assert _needs(bsdf).has_specular is specular


def test_analyse_lists_nested_bsdfs_and_emitters(variant):
    needs = _needs({"type": "blendbsdf", "weight": 0.3, "bsdf_0": {"type": "diffuse"}, "bsdf_1": {"type": "conductor"}})
    assert needs.bsdf_types == ("BlendBSDF", "SmoothConductor", "SmoothDiffuse")
    assert needs.emitter_types == ("ConstantBackgroundEmitter",)


# ------------------------------------------------------------------------------------- xml

QUAD_OBJ = "v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nvn 0 1 0\nf 1//1 3//1 2//1\nf 1//1 4//1 3//1\n"
SCENE_XML = """<scene version="3.0.0">
    <default name="film_width" value="40"/>
    <integrator type="direct"/>
    <sensor type="perspective">
        <float name="fov" value="50"/>
        <transform name="to_world"><lookat origin="0, 3, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm">
            <integer name="width" value="$film_width"/>
            <integer name="height" value="30"/>
            <rfilter type="gaussian"/>
        </film>
    </sensor>
    <shape type="obj"><string name="filename" value="meshes/floor.obj"/><bsdf type="diffuse"/></shape>
    <shape type="sphere"><point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.5"/>
        <bsdf type="roughplastic"/></shape>
    <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
</scene>
"""


@pytest.fixture
def xml_scene(tmp_path):
    return write_kitchen_scene(tmp_path)


def write_kitchen_scene(folder):
    """A user's scene folder: kitchen.xml (rough plastic sphere, 40x30 film) and the mesh it references."""
    (folder / "meshes").mkdir(parents=True)
    (folder / "meshes" / "floor.obj").write_text(QUAD_OBJ)
    path = folder / "kitchen.xml"
    path.write_text(SCENE_XML)
    return path


def test_xml_scene_gets_box_filtered_film_at_its_own_resolution(variant, xml_scene):
    (spec,) = xml_corpus([str(xml_scene.parent)], None)
    assert (spec.scene_id, spec.family, spec.resolution, spec.xml_path) == (
        "xml-kitchen",
        "xml",
        (40, 30),
        str(xml_scene),
    )
    scene = load_scene(spec)
    film = scene.sensors()[0].film()
    assert film.rfilter().class_name() == "BoxFilter" and list(film.size()) == [40, 30]
    image = render(scene)
    assert np.isfinite(image).all() and luminance(image).mean() > 0.05
    assert np.array_equal(image, render(load_scene(spec)))
    assert analyse(scene).has_specular and analyse(scene).bsdf_types == ("RoughPlastic", "SmoothDiffuse")


def test_xml_resolution_can_be_overridden(variant, xml_scene):
    (spec,) = xml_corpus([str(xml_scene.parent)], (24, 16))
    assert spec.resolution == (24, 16)
    assert list(load_scene(spec).sensors()[0].film().size()) == [24, 16]


def test_xml_corpus_finds_scenes_one_level_down_and_skips_fragments(tmp_path, xml_scene):
    sub = tmp_path / "attic"
    sub.mkdir()
    (sub / "scene.xml").write_text(SCENE_XML.replace("meshes/floor.obj", "../meshes/floor.obj"))
    (tmp_path / "materials.xml").write_text('<scene version="3.0.0"><bsdf type="diffuse" id="white"/></scene>')
    specs = xml_corpus([str(tmp_path)], (32, 32))
    assert [spec.scene_id for spec in specs] == ["xml-kitchen", "xml-attic"]


def test_xml_hash_follows_the_mesh_file_and_the_resolution(xml_scene):
    spec = SceneSpec("xml-kitchen", "xml", 0, (40, 30), str(xml_scene))
    before = scene_hash(spec)
    assert scene_hash(SceneSpec("xml-kitchen", "xml", 0, (40, 30), str(xml_scene))) == before
    assert scene_hash(SceneSpec("xml-kitchen", "xml", 0, (41, 30), str(xml_scene))) != before
    (xml_scene.parent / "meshes" / "floor.obj").write_text(QUAD_OBJ.replace("v 1 0 1", "v 1 0.1 1"))
    assert scene_hash(spec) != before


def test_missing_xml_file_is_named(variant, tmp_path):
    missing = tmp_path / "nowhere.xml"
    with pytest.raises(SceneError, match="nowhere.xml.*not found"):
        load_scene(SceneSpec("xml-nowhere", "xml", 0, RES, str(missing)))


def test_malformed_xml_is_named(variant, tmp_path, xml_scene):
    xml_scene.write_text(SCENE_XML.replace("</sensor>", ""))
    with pytest.raises(SceneError, match="kitchen.xml.*malformed"):
        load_scene(SceneSpec("xml-kitchen", "xml", 0, RES, str(xml_scene)))
    with pytest.raises(SceneError, match="kitchen.xml"):
        xml_corpus([str(tmp_path)], None)


def test_missing_mesh_file_is_named(variant, xml_scene):
    (xml_scene.parent / "meshes" / "floor.obj").unlink()
    spec = SceneSpec("xml-kitchen", "xml", 0, RES, str(xml_scene))
    with pytest.raises(SceneError, match="kitchen.xml.*meshes/floor.obj"):
        load_scene(spec)
    with pytest.raises(SceneError, match="floor.obj"):
        scene_hash(spec)


def test_scene_without_sensor_is_named(variant, tmp_path):
    path = tmp_path / "dark.xml"
    path.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    with pytest.raises(SceneError, match="dark.xml.*no <sensor>"):
        load_scene(SceneSpec("xml-dark", "xml", 0, RES, str(path)))
    with pytest.raises(SceneError, match="no Mitsuba scene"):
        xml_corpus([str(tmp_path)], None)


def test_studio_floats_objects_in_a_black_void_or_before_a_sky(variant):
    specs = [SceneSpec(f"studio-{seed}", "studio", seed, RES) for seed in range(12)]
    descriptions = [scene_description(spec) for spec in specs]
    void = [i for i, d in enumerate(descriptions) if "environment" not in d]
    assert 4 <= len(void) <= 10 and all(any(k.startswith("light_") for k in descriptions[i]) for i in void)
    for i in void[:3]:  # black environment: most of the frame sees nothing, and the rest is lit
        image = render(load_scene(specs[i]), spp=16)
        black = float((image.max(axis=-1) == 0).mean())
        assert 0.3 < black < 1.0 and luminance(image).max() > 0.05, (i, black)
    for seed, spec in enumerate(specs):
        if seed % 4 == 3:  # every fourth scene is purely diffuse
            assert not analyse(load_scene(spec)).has_specular, seed
