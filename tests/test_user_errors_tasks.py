"""Failures a user meets while rendering: broken scene files, failed tasks, an unreachable scheduler.

Each ends with one message naming the file (or address) and the problem, a non-zero exit and no
traceback; everything that could be done is done and cached, so a rerun does only the rest.
"""

import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from admc.pipeline.render.scenes import SceneError, load_scene, scene_hash, xml_corpus
from admc.stores import patches
from test_scenes import QUAD_OBJ, SCENE_XML, write_kitchen_scene

ADMC = str(Path(sys.executable).parent / "admc-pipe")


def admc(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([ADMC, *args], capture_output=True, text=True, timeout=300)


def tiny(workdir: Path, scenes: Path, *extra: str) -> list[str]:
    """--set options: only the user's scenes, 32x32, 2 spp + a 4 spp reference, everything in train."""
    settings = [
        f"run.workdir='{workdir}'",
        "run.scheduler=sync",
        "render.resolution=[32, 32]",
        "render.spp=[2]",
        "render.reference_spp=4",
        "corpus.n_scenes=0",
        f"corpus.xml_dirs=['{scenes}']",
        "tile.patch_size=32",
        "tile.crops_per_scene=2",
        "tile.split=[1.0, 0.0, 0.0]",
        *extra,
    ]
    return [item for setting in settings for item in ("--set", setting)]


def error_message(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 2, out.stdout + out.stderr
    assert "Traceback" not in out.stderr, out.stderr
    return out.stderr[out.stderr.index("error: ") :]


def test_a_failed_render_is_listed_with_its_scene_file_and_a_rerun_renders_only_it(tmp_path):
    scenes = tmp_path / "scenes"
    write_kitchen_scene(scenes / "good")
    bad = write_kitchen_scene(scenes / "bad")
    (bad.parent / "meshes" / "floor.obj").write_bytes(b"\x00\x01 this is not a mesh\n")

    message = error_message(admc("render", *tiny(tmp_path / "work", scenes)))
    lines = message.splitlines()
    assert lines[0].startswith("error: 2 task(s) failed, 0 skipped") and "2 of 4 are published" in lines[0]
    assert len(lines) == 3
    for line, level in zip(lines[1:], ("2 spp", "reference 4 spp")):
        assert line.startswith(
            f"  render 'xml-bad @ {level}' ({bad}): Mitsuba could not load the scene: <shape> "
            f"naming {bad.parent / 'meshes' / 'floor.obj'}: failed to instantiate shape plugin "
            'of type "obj": '
        )
    assert (tmp_path / "work" / "renders" / "xml-good" / "reference.exr").is_file(), "the good scene is rendered"

    (bad.parent / "meshes" / "floor.obj").write_text(QUAD_OBJ)
    out = admc("render", *tiny(tmp_path / "work", scenes))
    assert out.returncode == 0, out.stderr
    assert "(2 rendered now, 2 cached)" in out.stdout


def test_a_broken_xml_in_a_scene_folder_leaves_out_only_that_scene(tmp_path, variant):
    scenes, work = tmp_path / "scenes", tmp_path / "work"
    write_kitchen_scene(scenes / "good")
    malformed = write_kitchen_scene(scenes / "malformed")
    malformed.write_text(SCENE_XML.replace("</sensor>", ""))
    missing = write_kitchen_scene(scenes / "missing")
    (missing.parent / "meshes" / "floor.obj").unlink()

    message = error_message(admc("dataset", *tiny(work, scenes)))
    assert message.splitlines() == [
        "error: 2 scene file(s) left out of the corpus (fix and rerun: only what is missing runs):",
        f"  {malformed}: malformed XML (mismatched tag: line 17, column 2)",
        f"  {missing}: referenced file 'meshes/floor.obj' not found (looked in {missing.parent})",
    ]
    assert patches.list_scenes(work / "patches.zarr", "train") == ["xml-good"]

    malformed.write_text(SCENE_XML)
    (missing.parent / "meshes" / "floor.obj").write_text(QUAD_OBJ)
    out = admc("dataset", *tiny(work, scenes))
    assert out.returncode == 0, out.stderr
    assert "6 tasks run, 3 cached" in out.stdout
    assert patches.list_scenes(work / "patches.zarr", "train") == ["xml-good", "xml-malformed", "xml-missing"]


def test_an_address_where_no_scheduler_listens_is_named_at_once(tmp_path):
    with socket.socket() as taken:  # bound, never listening: a connect is refused at once
        taken.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{taken.getsockname()[1]}"
        write_kitchen_scene(tmp_path / "scenes")
        message = error_message(admc("render", *tiny(tmp_path / "work", tmp_path / "scenes"), "--scheduler", address))
    assert message.startswith(f"error: no dask scheduler answers at {address} (run.scheduler): ")
    assert not (tmp_path / "work" / "cache" / "render").exists()


PATH_SCENE = SCENE_XML.replace("<integrator", '<path value="../common"/>\n    <integrator')


def test_path_search_folders_resolve_like_mitsuba_and_the_hash_follows_the_resolved_file(tmp_path, variant):
    """Mitsuba's test scenes add a search folder with <path>; it goes before the XML's own folder."""
    import mitsuba as mi

    scene = tmp_path / "scenes" / "cbox" / "cbox.xml"
    scene.parent.mkdir(parents=True)
    scene.write_text(PATH_SCENE)
    (tmp_path / "scenes" / "common" / "meshes").mkdir(parents=True)
    searched = tmp_path / "scenes" / "common" / "meshes" / "floor.obj"
    searched.write_text(QUAD_OBJ.replace(" 0 ", " -0.5 "))  # a floor half a unit lower
    (spec,) = xml_corpus([str(tmp_path / "scenes")], (32, 32))
    assert spec.scene_id == "xml-cbox"
    np.testing.assert_array_equal(np.array(load_scene(spec).bbox().min), np.array(mi.load_file(str(scene)).bbox().min))
    assert load_scene(spec).bbox().min[1] == -0.5

    shadowed = scene.parent / "meshes" / "floor.obj"  # Mitsuba finds the <path> folder's file first
    shadowed.parent.mkdir()
    shadowed.write_text(QUAD_OBJ)
    before = scene_hash(spec)
    np.testing.assert_array_equal(np.array(load_scene(spec).bbox().min), np.array(mi.load_file(str(scene)).bbox().min))
    shadowed.write_text(QUAD_OBJ.replace(" 0 ", " 0.25 "))
    assert scene_hash(spec) == before
    searched.write_text(QUAD_OBJ.replace(" 0 ", " -0.25 "))
    assert scene_hash(spec) != before


def test_an_included_file_names_meshes_on_the_scene_files_search_path(tmp_path, variant):
    """As Mitsuba loads it: an included fragment's `filename` resolves from the including scene's folder."""
    import mitsuba as mi

    write_kitchen_scene(tmp_path)
    scene = tmp_path / "kitchen.xml"
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "floor.xml").write_text(
        '<scene version="3.0.0"><shape type="obj"><string name="filename" value="meshes/floor.obj"/></shape></scene>'
    )
    scene.write_text(
        SCENE_XML.replace(
            '<shape type="obj"><string name="filename" value="meshes/floor.obj"/><bsdf type="diffuse"/></shape>',
            '<include filename="parts/floor.xml"/>',
        )
    )
    (spec,) = xml_corpus([str(tmp_path)], (32, 32))
    assert len(load_scene(spec).shapes()) == len(mi.load_file(str(scene)).shapes()) == 2
    (tmp_path / "parts" / "meshes").mkdir()
    (tmp_path / "parts" / "meshes" / "floor.obj").write_text(QUAD_OBJ)  # next to the fragment: Mitsuba ignores it
    (tmp_path / "meshes" / "floor.obj").unlink()
    with pytest.raises(RuntimeError, match="floor.obj"):
        mi.load_file(str(scene))
    with pytest.raises(SceneError, match=f"{tmp_path / 'parts' / 'floor.xml'}: referenced file 'meshes/floor.obj'"):
        xml_corpus([str(tmp_path)], (32, 32))
