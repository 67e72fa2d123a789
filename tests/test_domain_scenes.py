"""scripts/make_domain_scenes.py: the cbox fine-tuning domain is deterministic and renders through admc's
own XML corpus path (discovery, film swap, split integrator) like any user's scenes."""
import subprocess
import sys
from pathlib import Path

import numpy as np

from admc.pipeline.config import load_config
from admc.pipeline.stages.render import render_corpus
from admc.stores.exr import read_exr

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "make_domain_scenes.py"
NAMES = ["cbox-0-000.xml", "cbox-0-001.xml", "cbox-0-002.xml"]


def make_scenes(out: Path, seed: int) -> dict[str, bytes]:
    """Run the script for 3 scenes; the files it wrote, by name."""
    done = subprocess.run([sys.executable, str(SCRIPT), str(out), "--scenes", "3", "--seed", str(seed)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return {path.name: path.read_bytes() for path in sorted(out.iterdir())}


def test_the_same_seed_writes_the_same_files_and_another_seed_other_ones(tmp_path):
    first = make_scenes(tmp_path / "a", seed=0)
    assert list(first) == NAMES
    assert make_scenes(tmp_path / "b", seed=0) == first
    other = make_scenes(tmp_path / "c", seed=1)
    assert list(other) == [name.replace("-0-", "-1-") for name in NAMES]
    assert set(other.values()).isdisjoint(first.values())


def test_cbox_scenes_load_and_render_with_the_split_integrator(tmp_path, variant):
    make_scenes(tmp_path / "cbox", seed=0)
    cfg = load_config(None, [f"run.workdir='{tmp_path / 'work'}'", "run.scheduler=sync", "render.resolution=[32, 32]",
                             "render.spp=[4]", "render.reference_spp=8", "corpus.n_scenes=0",
                             f"corpus.xml_dirs=['{tmp_path / 'cbox'}']"])
    result = render_corpus(cfg, progress=False)
    assert result.executed == 6 and len(result.sidecars) == 6
    specular = {}
    for sidecar in result.sidecars:
        name = "reference" if sidecar["reference"] else "spp0004"
        layers = read_exr(result.renders_dir / sidecar["scene_id"] / f"{name}.exr")
        image = layers["diffuse"] + layers.get("specular", 0.0)
        assert image.shape == (32, 32, 3) and all(np.isfinite(a).all() for a in layers.values())
        assert sidecar["nonfinite"] == {} and image.mean() > 0.01, (sidecar["scene_id"], image.mean())
        specular[sidecar["scene_id"]] = sidecar["has_specular"]
    assert specular == {"xml-cbox-0-000": True, "xml-cbox-0-001": True, "xml-cbox-0-002": False}, \
        "every third scene is diffuse-only, the others have a specular object"
