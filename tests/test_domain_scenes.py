"""scripts/make_domain_scenes.py: the cbox fine-tuning domain is deterministic and renders through admc's
own XML corpus path (discovery, film swap, split integrator) like any user's scenes."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from admc.pipeline.config import load_config
from admc.pipeline.stages.render import render_corpus
from admc.stores.exr import read_exr

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "make_domain_scenes.py"
NAMES = ["cbox-0-000.xml", "cbox-0-001.xml", "cbox-0-002.xml"]


def make_scenes(out: Path, seed: int = 0, domain: str = "cbox") -> dict[str, bytes]:
    """Run the script for 3 frames of `domain`; the files it wrote, by name."""
    done = subprocess.run(
        [sys.executable, str(SCRIPT), str(out), "--domain", domain, "--frames", "3", "--seed", str(seed)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return {path.name: path.read_bytes() for path in sorted(out.iterdir())}


def render_frames(tmp_path: Path, frames: Path):
    """The folder's frames rendered through the XML corpus: 32x32, 4 spp and an 8-spp reference."""
    cfg = load_config(
        None,
        [
            f"run.workdir='{tmp_path / 'work'}'",
            "run.scheduler=sync",
            "render.resolution=[32, 32]",
            "render.spp=[4]",
            "render.reference_spp=8",
            "corpus.n_scenes=0",
            f"corpus.xml_dirs=['{frames}']",
        ],
    )
    return render_corpus(cfg, progress=False)


def test_the_same_seed_writes_the_same_files_and_another_seed_other_ones(tmp_path):
    first = make_scenes(tmp_path / "a", seed=0)
    assert list(first) == NAMES
    assert make_scenes(tmp_path / "b", seed=0) == first
    other = make_scenes(tmp_path / "c", seed=1)
    assert list(other) == [name.replace("-0-", "-1-") for name in NAMES]
    assert set(other.values()).isdisjoint(first.values())


def test_cbox_scenes_load_and_render_with_the_split_integrator(tmp_path, variant):
    make_scenes(tmp_path / "cbox", seed=0)
    result = render_frames(tmp_path, tmp_path / "cbox")
    assert result.executed == 6 and len(result.sidecars) == 6
    specular = {}
    for sidecar in result.sidecars:
        name = "reference" if sidecar["reference"] else "spp0004"
        layers = read_exr(result.renders_dir / sidecar["scene_id"] / f"{name}.exr")
        image = layers["diffuse"] + layers.get("specular", 0.0)
        assert image.shape == (32, 32, 3) and all(np.isfinite(a).all() for a in layers.values())
        assert sidecar["nonfinite"] == {} and image.mean() > 0.01, (sidecar["scene_id"], image.mean())
        specular[sidecar["scene_id"]] = sidecar["has_specular"]
    assert specular == {"xml-cbox-0-000": True, "xml-cbox-0-001": True, "xml-cbox-0-002": False}, (
        "every third scene is diffuse-only, the others have a specular object"
    )


@pytest.mark.parametrize("domain", ["interior", "product", "exterior"])
def test_a_domain_is_one_set_whose_frames_render_through_the_xml_corpus(tmp_path, variant, domain):
    """Each studio domain writes its frames plus the set's shared texture (EXR) and mesh (OBJ) files, the
    same bytes for the same seed; every frame loads and renders with the split integrator, non-black and
    finite, and the set's frames differ (cameras, lights) while sharing its files."""
    out = tmp_path / domain
    files = make_scenes(out, domain=domain)
    frames = [name for name in files if name.endswith(".xml")]
    assert frames == [f"{domain}-0-{i:03d}.xml" for i in range(3)] and len(set(files[f] for f in frames)) == 3
    shared = [name for name in files if not name.endswith(".xml")]
    assert shared and all(name.endswith((".exr", ".obj")) for name in shared)
    assert all(any(name in files[f].decode() for f in frames) for name in shared), "every asset is used"
    assert make_scenes(tmp_path / "again", domain=domain) == files
    result = render_frames(tmp_path, out)
    assert result.executed == 6
    for sidecar in result.sidecars:
        layers = read_exr(
            result.renders_dir / sidecar["scene_id"] / ("reference.exr" if sidecar["reference"] else "spp0004.exr")
        )
        image = layers["diffuse"] + layers.get("specular", 0.0)
        assert all(np.isfinite(a).all() for a in layers.values()) and image.mean() > 0.005, sidecar["scene_id"]
        assert sidecar["has_specular"], "every domain has glossy, metal or glass surfaces"
