"""Blender Cycles as a corpus renderer: procedural .blend scenes (scripts/make_blend_scenes.py) rendered by
real Cycles at 32x32 into the EXR + sidecar the Mitsuba path writes, tiled by `admc-pipe dataset`; a killed
Cycles render resumes; without Blender a .blend corpus is one message."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_cli import ADMC

from admc.pipeline.render.blender.locate import blender_command
from admc.pipeline.render.blender.passes import combine, coverage
from admc.pipeline.render.blender.cycles_tasks import subrender_plan
from admc.stores.exr import read_exr

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "make_blend_scenes.py"
PYTHON = str(REPO / ".venv" / "bin" / "python")


def settings(workdir: Path, scenes: Path, *extra: str) -> list[str]:
    values = [
        f"run.workdir='{workdir}'",
        "run.scheduler=sync",
        "corpus.n_scenes=0",
        f"corpus.blend_dirs=['{scenes}']",
        "render.resolution=[32, 32]",
        "render.spp=[2, 4]",
        "render.reference_spp=16",
        "render.blender_threads=1",
        *extra,
    ]
    return [arg for value in values for arg in ("--set", value)]


def admc(*args: str, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([ADMC, *args], capture_output=True, text=True, timeout=600, env=env)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    if blender_command() is None:
        pytest.skip("no Blender (bash scripts/setup.sh --blender installs .venv-blender)")
    folder = tmp_path_factory.mktemp("blends")
    out = subprocess.run(
        [PYTHON, str(SCRIPT), str(folder), "--scenes", "2", "--resolution", "32", "32"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert sorted(p.name for p in folder.glob("*.blend")) == ["interior-000.blend", "product-001.blend"]
    return folder


@pytest.fixture(scope="module")
def rendered(scenes, tmp_path_factory):
    workdir = tmp_path_factory.mktemp("cycles")
    out = admc("render", *settings(workdir, scenes))
    assert out.returncode == 0, out.stderr
    assert "(6 rendered now, 0 cached)" in out.stdout
    return workdir


def test_the_scene_script_is_deterministic(scenes, tmp_path):
    for seed in ("0", "1"):
        out = subprocess.run(
            [PYTHON, str(SCRIPT), str(tmp_path / seed), "--scenes", "2", "--resolution", "32", "32", "--seed", seed],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert out.returncode == 0, out.stderr
    first = json.loads((scenes / "scenes.json").read_text())
    assert json.loads((tmp_path / "0" / "scenes.json").read_text()) == first
    assert json.loads((tmp_path / "1" / "scenes.json").read_text()) != first
    assert any(name.startswith("Area") for name, _, _ in first["interior-000"])


def test_cycles_renders_are_what_the_mitsuba_path_writes(rendered):
    for scene in ("blend-interior-000", "blend-product-001"):
        folder = rendered / "renders" / scene
        noisy, reference = read_exr(folder / "spp0004.exr"), read_exr(folder / "reference.exr")
        sidecar = json.loads((folder / "spp0004.json").read_text())
        ref_sidecar = json.loads((folder / "reference.json").read_text())
        assert (
            set(noisy)
            == set(reference)
            == {"diffuse", "specular", "albedo", "normal", "depth", "coverage", "diffuse_var", "specular_var"}
        )
        assert noisy["diffuse"].shape == (32, 32, 3)
        assert sidecar["spp"] == 4 and ref_sidecar["reference"] and sidecar["seed"] != ref_sidecar["seed"]
        assert sidecar["variant"].startswith("cycles-cpu (Blender 5.0")
        assert len(sidecar["subrenders"]) == 4 and len({seed for _, seed in sidecar["subrenders"]}) == 4
        assert all(np.isfinite(layer).all() for layer in noisy.values())
        # noisy and reference agree on average (independent seeds, the same scene); the reference is less noisy
        for branch in ("diffuse", "specular"):
            assert abs(noisy[branch].mean() - reference[branch].mean()) < 0.25 * reference[branch].mean() + 1e-3
        assert noisy["diffuse_var"].mean() > 2 * reference["diffuse_var"].mean() > 0
        hit = reference["coverage"][..., 0] > 0
        assert hit.mean() > 0.5 and (reference["coverage"][reference["depth"][..., 0] > 0] == 1).all()
        assert (reference["depth"][~hit] == 0).all()
        centre = reference["normal"][8:24, 8:24][hit[8:24, 8:24]]
        assert (centre[:, 2] > -0.2).mean() > 0.95  # camera space: what the camera sees faces it
        assert 0 <= reference["albedo"].min() and reference["albedo"].max() <= 1.0


def test_subrenders_combine_to_the_mean_and_the_variance_of_the_mean():
    rng = np.random.default_rng(0)
    samples = rng.gamma(2.0, 1.0, size=(4, 8, 8, 3))  # four sub-renders of one sample each
    parts = [({"diffuse": s, "specular": 2 * s, "coverage": np.ones((8, 8, 1))}, 1) for s in samples]
    out = combine(parts)
    np.testing.assert_allclose(out["diffuse"], samples.mean(0), rtol=1e-5)
    np.testing.assert_allclose(out["diffuse_var"], samples.var(0, ddof=1) / 4, rtol=1e-4)
    np.testing.assert_allclose(out["specular_var"], 4 * out["diffuse_var"], rtol=1e-5)
    plan = subrender_plan(10, 7, 4)
    assert [spp for spp, _ in plan] == [3, 3, 2, 2] and plan == subrender_plan(10, 7, 4)
    assert subrender_plan(2, 7, 4) == subrender_plan(2, 7, 2) and len(subrender_plan(1, 7, 4)) == 1


def test_coverage_is_zero_only_where_the_environment_is_seen_directly():
    sky = np.full((1, 3, 3), 0.7, np.float32)
    depth = np.array([[[2.0], [0.0], [0.0]]], np.float32)  # a surface, the sky, a mirror showing the sky
    combined = np.array([[[0.3] * 3, [0.7] * 3, [0.5] * 3]], np.float32)
    environment = np.array([[[0.0] * 3, [0.7] * 3, [0.0] * 3]], np.float32)  # Cycles' pass: the sky seen directly
    assert coverage(depth, combined, environment)[0, :, 0].tolist() == [1.0, 0.0, 1.0]
    assert coverage(depth, sky, sky)[0, :, 0].tolist() == [1.0, 0.0, 0.0]


def test_dataset_tiles_cycles_renders_like_mitsuba_ones(rendered, scenes):
    out = admc(
        "dataset",
        *settings(rendered, scenes, "tile.patch_size=32", "tile.crops_per_scene=2", "tile.split=[0.5, 0.5, 0.0]"),
    )
    assert out.returncode == 0, out.stderr
    assert "(0 rendered now" not in out.stdout  # the renders are cached: only the tiling ran
    from admc.stores import patches

    store = rendered / "patches.zarr"
    held = {scene for split in ("train", "val", "test") for scene in patches.list_scenes(store, split)}
    assert held == {"blend-interior-000", "blend-product-001"}
    assert "sanitized values: none" in out.stdout


def test_a_killed_cycles_render_resumes(scenes, tmp_path):
    cache = tmp_path / "cache" / "render"
    proc = subprocess.Popen(
        [ADMC, "render", *settings(tmp_path, scenes, "render.reference_spp=64")],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 300
        while not (list(cache.glob("*/_task.json")) and list((tmp_path / "cache" / ".tmp").glob("*/_subrenders/*"))):
            assert proc.poll() is None, "the render finished before it could be killed"
            assert time.monotonic() < deadline, "no Cycles render started"
            time.sleep(0.02)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # admc-pipe and the Blender it runs
        proc.wait()
    done_before = len(list(cache.glob("*/_task.json")))
    assert 1 <= done_before < 6
    out = admc("render", *settings(tmp_path, scenes, "render.reference_spp=64"))
    assert out.returncode == 0, out.stderr
    assert f"({6 - done_before} rendered now, {done_before} cached)" in out.stdout
    assert len(list(cache.glob("*/_task.json"))) == 6


def test_without_blender_a_blend_corpus_is_one_message(scenes, tmp_path):
    env = {**os.environ, "ADMC_BLENDER": sys.executable}  # a Python without bpy
    out = admc("render", *settings(tmp_path, scenes), env=env)
    assert out.returncode == 2 and "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert "(corpus.blend_dirs): rendering .blend scenes needs Blender (bpy)" in out.stderr
    assert "bash scripts/setup.sh --blender" in out.stderr
    out = admc("render", *settings(tmp_path, scenes, "render.blender='/no/blender'"))
    assert out.returncode == 2 and "/no/blender: no such Blender executable or Python (render.blender)" in out.stderr
