"""User errors around the patch store, as `admc-pipe` reports them: a damaged chunk, a patch size the
images cannot hold or the critic cannot take, a leftover empty store, a split that leaves training
without scenes. Each is one message naming the store/scene/array or config key, no traceback."""

import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import build_tiny_store, preset, tiny_store_overrides
from admc.stores import patches

ADMC = str(Path(__file__).resolve().parents[1] / ".venv" / "bin" / "admc-pipe")


def admc(*args, overrides=()):
    sets = [item for value in overrides for item in ("--set", value)]
    return subprocess.run([ADMC, *args, *sets], capture_output=True, text=True, timeout=300)


def flip_bytes(file: Path, offset: int, count: int = 8) -> None:
    """Invert `count` bytes at `offset` (negative: from the end), as a failing disk or a bad copy would."""
    data = bytearray(file.read_bytes())
    start = offset % len(data)
    data[start : start + count] = bytes(b ^ 0xFF for b in data[start : start + count])
    file.write_bytes(bytes(data))


def shard(store: Path, split: str, scene: str, array: str) -> Path:
    (file,) = [p for p in (store / split / scene / array / "c").rglob("*") if p.is_file()]
    return file


@pytest.fixture
def tiny(tmp_path, variant):
    """(store, the overrides that built it, a scene of its train split)."""
    overrides = tiny_store_overrides(tmp_path / "w", size=32, patch=32)
    store = build_tiny_store(tmp_path / "w", size=32, patch=32)
    return store, overrides, patches.list_scenes(store, "train")[0]


def test_a_damaged_chunk_is_named_and_dataset_tiles_that_scene_again(tiny):
    store, overrides, scene = tiny
    before = np.asarray(patches.PatchReader(store, "train")[0]["noisy"])
    # Bytes inside a compressed chunk: zarr decodes them to wrong values without any error.
    flip_bytes(shard(store, "train", scene, "noisy_diffuse"), 100)

    out = admc("dataset", "--summary", overrides=overrides)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    message = " ".join(out.stderr.split())
    assert f"patch store {store}: scene train/{scene}, array noisy_diffuse:" in message
    assert "checksums" in message and "run `admc-pipe dataset` with the same config" in message

    out = admc("dataset", overrides=overrides)
    assert out.returncode == 0, out.stderr
    assert "1 tasks run" in out.stdout, "only the damaged scene's tile task; its renders are cached"
    assert f"re-tiled damaged scenes from their cached renders: train/{scene} (noisy_diffuse)" in out.stdout
    assert patches.damaged_arrays(store, "train", scene) == []
    np.testing.assert_array_equal(patches.PatchReader(store, "train")[0]["noisy"], before)

    again = admc("dataset", overrides=overrides)
    assert again.returncode == 0 and "0 tasks run" in again.stdout and "re-tiled" not in again.stdout


def test_train_tiles_a_damaged_scene_again_before_training_and_says_so(tiny):
    store, overrides, scene = tiny
    flip_bytes(shard(store, "train", scene, "ref_diffuse"), 100)
    out = admc("train", overrides=[*overrides, "train.steps=2", "train.val_every=0"])
    assert out.returncode == 0, out.stderr
    assert f"re-tiled damaged scenes from their cached renders: train/{scene} (ref_diffuse)" in out.stdout
    assert patches.damaged_arrays(store, "train", scene) == []


def test_training_on_an_undecodable_chunk_names_store_scene_and_array(tiny, tmp_path):
    from admc.model.training.trainer import train
    from dataclasses import replace

    store, _, scene = tiny
    flip_bytes(shard(store, "train", scene, "features"), -10)  # the shard index: zarr's crc32c refuses it
    model, settings = preset("default")
    settings = replace(settings, steps=2, val_every=0, branches=("diffuse",), l1_warmup_steps=2)
    with pytest.raises(patches.PatchStoreError) as caught:
        train(store, tmp_path / "run", settings, replace(model, channels=4, blocks=1), progress=False)
    assert str(caught.value).startswith(f"patch store {store}: scene train/{scene}, array features: cannot be decoded")
    assert "admc-pipe dataset" in str(caught.value)


def test_a_patch_larger_than_the_render_is_refused_before_anything_is_created(tmp_path):
    overrides = tiny_store_overrides(tmp_path / "w", size=32, patch=64)
    out = admc("dataset", overrides=overrides)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert (
        "config key 'tile.patch_size': 64 is larger than the image, render.resolution is 32x32; use at most 32 "
        "or raise render.resolution" in " ".join(out.stderr.split())
    )
    assert not (tmp_path / "w").exists(), "nothing rendered, no store created"


def test_a_patch_larger_than_an_xml_film_names_the_scene_file(tmp_path):
    from test_scenes import write_kitchen_scene

    xml = write_kitchen_scene(tmp_path / "my_scenes")  # a 40x30 film
    out = admc(
        "dataset",
        overrides=[
            f"run.workdir='{tmp_path / 'w'}'",
            "corpus.n_scenes=0",
            f"corpus.xml_dirs=['{xml.parent}']",
            "corpus.xml_resolution='film'",
            "tile.patch_size=32",
        ],
    )
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert (
        f"config key 'tile.patch_size': 32 is larger than the image, scene {xml} renders at its film's 40x30 "
        "(corpus.xml_resolution = film); set corpus.xml_resolution = render" in " ".join(out.stderr.split())
    )
    assert not (tmp_path / "w").exists()


def test_an_empty_store_left_by_a_failed_run_does_not_pin_its_patch_size(tmp_path, variant):
    from admc.pipeline.config import load_config
    from admc.pipeline.stages.dataset import store_attributes

    overrides = tiny_store_overrides(tmp_path / "w", size=32, patch=32)
    store = tmp_path / "w" / "patches.zarr"
    old = load_config(None, tiny_store_overrides(tmp_path / "w", size=32, patch=128))
    patches.create_store(store, store_attributes(old))  # what a run that failed before tiling left behind
    out = admc("dataset", overrides=overrides)
    assert out.returncode == 0, out.stderr
    assert patches.PatchReader(store, "train").attrs["patch_size"] == 32
    # once it holds scenes, a store keeps its settings
    out = admc("dataset", overrides=[*overrides, "tile.crops_per_scene=2"])
    message = " ".join(out.stderr.split())
    assert out.returncode == 2 and "existing store differs in tile.crops_per_scene" in message
    assert "use another store (tile.store) or move this one away" in message


@pytest.mark.parametrize("command", ["dataset", "train"])
def test_a_patch_size_the_critic_cannot_take_is_refused_when_the_config_loads(tmp_path, command):
    out = admc(command, overrides=tiny_store_overrides(tmp_path / "w", size=32, patch=16))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "config key 'tile.patch_size': must be a multiple of 32 (the critic halves it 5 times), got 16" in " ".join(
        out.stderr.split()
    )
    assert not (tmp_path / "w").exists()


def test_train_refuses_a_split_without_validation_scenes_before_rendering(tmp_path):
    overrides = [*tiny_store_overrides(tmp_path / "w", size=32, patch=32), "tile.split=[1.0, 0.0, 0.0]"]
    out = admc("train", overrides=overrides)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    message = " ".join(out.stderr.split())
    assert (
        "config key 'tile.split': no scene of the 4-scene corpus (tile.split = [1.0, 0.0, 0.0], tile.seed = 17) "
        "falls in the val split, which train.val_every = 100 validates on" in message
    )
    assert not (tmp_path / "w").exists()


def test_train_on_an_empty_corpus_says_to_name_the_frames(tmp_path):
    # configs/domain.toml sets corpus.n_scenes = 0: without a folder of frames there is nothing to train on
    overrides = [*tiny_store_overrides(tmp_path / "w", size=32, patch=32), "corpus.n_scenes=0"]
    out = admc("train", overrides=overrides)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    message = " ".join(out.stderr.split())
    assert "the corpus is empty: corpus.n_scenes = 0 and no scene in corpus.xml_dirs or corpus.blend_dirs" in message
    assert not (tmp_path / "w").exists()
