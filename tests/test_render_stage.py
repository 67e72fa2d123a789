"""The render stage end to end: a tiny corpus through the cache and runner into EXRs and sidecars."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from admc.pipeline.config import load_config
from admc.pipeline.stages.corpus import open_cache
from admc.pipeline.stages.render import render_corpus
from admc.stores.exr import read_exr

ADMC = str(Path(sys.executable).parent / "admc-pipe")


def tiny(workdir, *extra):
    return [
        f"run.workdir='{workdir}'",
        "run.scheduler=sync",
        "render.resolution=[32, 32]",
        "render.spp=[2, 4]",
        "render.reference_spp=16",
        "corpus.families=['room']",
        *extra,
    ]


def test_tiny_corpus_renders_every_layer_and_reruns_nothing(tmp_path, variant):
    cfg = load_config(None, tiny(tmp_path, "corpus.n_scenes=2"))
    first = render_corpus(cfg, progress=False)
    assert first.executed == 6 and first.cached == 0
    for sidecar in first.sidecars:
        scene = first.renders_dir / sidecar["scene_id"]
        name = "reference" if sidecar["reference"] else f"spp{sidecar['spp']:04d}"
        layers = read_exr(scene / f"{name}.exr")
        expected = {"diffuse", "albedo", "normal", "depth", "coverage", "diffuse_var"}
        if sidecar["has_specular"]:
            expected |= {"specular", "specular_var"}
        assert set(layers) == expected
        assert all(np.isfinite(a).all() for a in layers.values())
        assert layers["diffuse"].shape == (32, 32, 3)
        assert json.loads((scene / f"{name}.json").read_text())["spp"] == sidecar["spp"]
        assert sidecar["render_seconds"] > 0 and sidecar["variant"] == variant
    seeds = [s["seed"] for s in first.sidecars]
    assert len(set(seeds)) == len(seeds), "every (scene, spp) needs its own seed"
    again = render_corpus(cfg, progress=False)
    assert again.executed == 0 and again.cached == 6


def test_killed_render_resumes_with_only_unfinished_tasks(tmp_path, variant):
    args = [item for s in tiny(tmp_path, "corpus.n_scenes=3", "render.reference_spp=4096") for item in ("--set", s)]
    proc = subprocess.Popen(
        [ADMC, "render", *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True
    )
    cache = open_cache(load_config(None, tiny(tmp_path, "corpus.n_scenes=3", "render.reference_spp=4096")))
    deadline = time.time() + 240
    while time.time() < deadline and len(cache.entries()) < 2:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done_before = {e["key"] for e in cache.entries()}
    assert 2 <= len(done_before) < 9, "the kill must land mid-run"
    cfg = load_config(None, tiny(tmp_path, "corpus.n_scenes=3", "render.reference_spp=4096"))
    resumed = render_corpus(cfg, progress=False)
    assert resumed.cached == len(done_before)
    assert resumed.executed == 9 - len(done_before)


def test_cli_render_then_cache_listing_and_clear(tmp_path, variant):
    args = [item for s in tiny(tmp_path, "corpus.n_scenes=1") for item in ("--set", s)]
    out = subprocess.run([ADMC, "render", *args], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "rendered 3 images of 1 scenes" in out.stdout
    listing = subprocess.run([ADMC, "cache", *args], capture_output=True, text=True, timeout=60)
    assert "render" in listing.stdout and "3" in listing.stdout
    cleared = subprocess.run([ADMC, "cache", "--clear", *args], capture_output=True, text=True, timeout=60)
    assert "removed 3" in cleared.stdout


def test_normals_are_in_view_space(variant):
    """Cornell box: the left wall faces right (+x), the ceiling down (-y); nothing visible faces away."""
    import mitsuba as mi
    from admc.pipeline.render import integrator
    from admc.pipeline.render.tasks import view_space_normals

    integrator.register()
    box = mi.cornell_box()
    box["sensor"]["film"].update({"width": 32, "height": 32, "rfilter": {"type": "box"}})
    scene = mi.load_dict(box)
    normal = view_space_normals(integrator.render_buffers(scene, 4, 1)["normal"], scene)
    np.testing.assert_allclose(normal[16, 1], [1, 0, 0], atol=1e-3)  # red wall on the left faces right
    np.testing.assert_allclose(normal[16, 30], [-1, 0, 0], atol=1e-3)  # green wall on the right faces left
    np.testing.assert_allclose(normal[1, 16], [0, -1, 0], atol=1e-3)  # ceiling faces down
    assert normal[..., 2].min() > -1e-3, "visible surfaces face the viewer (+z)"
