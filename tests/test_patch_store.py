"""Patch store on real Zarr v3 directories: round trips, refusals, parallel writers, atomicity."""

import concurrent.futures
import hashlib
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from zarr.storage import LocalStore

from admc.common.buffers import sanitize
from admc.model import transforms as T
from admc.stores import patches as P

PATCH = 128
SPEC = T.transform_spec()
ROOT_ATTRS = {"transform": SPEC, "patch_size": PATCH, "code_version": "test-1", "render_fingerprint": "abc"}


def synthetic_scene(seed: int, crops: int = 3, spp_levels=(1, 4), specular: bool = True) -> dict:
    """Patch arrays in the store's layout: every spp row of a crop points at that crop's reference."""
    rng = np.random.default_rng(seed)
    n = crops * len(spp_levels)
    scene = {
        "noisy_diffuse": rng.uniform(0, 12, (n, 3, PATCH, PATCH)).astype(np.float16),
        "features": rng.uniform(0, 1, (n, 7, PATCH, PATCH)).astype(np.float16),
        "ref_diffuse": rng.uniform(0, 12, (crops, 3, PATCH, PATCH)).astype(np.float16),
        "spp": np.repeat(np.asarray(spp_levels), crops),
        "crop": np.tile(np.arange(crops), len(spp_levels)),
        "origin": np.stack([np.arange(crops) * PATCH, np.zeros(crops, int)], axis=1),
    }
    if specular:
        scene["noisy_specular"] = rng.uniform(0, 12, (n, 3, PATCH, PATCH)).astype(np.float16)
        scene["ref_specular"] = rng.uniform(0, 12, (crops, 3, PATCH, PATCH)).astype(np.float16)
    return scene


def scene_attrs(name: str) -> dict:
    return {
        "scene_hash": f"hash-{name}",
        "image_size": [384, 128],
        "sanitization": {"diffuse": {"nan": 2, "posinf": 1}},
    }


def write_synthetic(path: str, split: str, scene_id: str, seed: int, specular: bool = True) -> str:
    P.write_scene(path, split, scene_id, synthetic_scene(seed, specular=specular), scene_attrs(scene_id))
    return scene_id


def assert_rows_match(reader: P.PatchReader, expected: dict[str, dict], branch: str) -> None:
    i = 0
    for scene in reader.scenes:
        arrays = expected[scene]
        for row in range(len(arrays["spp"])):
            item = reader[i]
            assert item["scene"] == scene and item["spp"] == arrays["spp"][row]
            np.testing.assert_array_equal(item["noisy"], arrays[f"noisy_{branch}"][row].astype(np.float32))
            np.testing.assert_array_equal(item["features"], arrays["features"][row].astype(np.float32))
            ref = arrays[f"ref_{branch}"][arrays["crop"][row]].astype(np.float32)
            np.testing.assert_array_equal(item["reference"], ref)
            assert item["noisy"].dtype == np.float32 and item["features"].shape == (7, PATCH, PATCH)
            i += 1
    assert i == len(reader)


@pytest.fixture
def store(tmp_path) -> str:
    path = str(tmp_path / "patches.zarr")
    P.create_store(path, ROOT_ATTRS)
    return path


def test_write_read_back_exact_both_branches(store):
    expected = {"a": synthetic_scene(1), "b": synthetic_scene(2, specular=False)}
    for name, arrays in expected.items():
        P.write_scene(store, "train", name, arrays, scene_attrs(name))

    diffuse = P.PatchReader(store, "train", expect_transform=SPEC)
    assert diffuse.scenes == ["a", "b"] and len(diffuse) == 12
    assert_rows_match(diffuse, expected, "diffuse")
    specular = P.PatchReader(store, "train", branch="specular")
    assert specular.scenes == ["a"] and len(specular) == 6
    assert_rows_match(specular, expected, "specular")
    assert len(P.PatchReader(store, "val")) == 0

    group = zarr.open_group(store=LocalStore(store, read_only=True), mode="r")["train/b"]
    assert group.attrs["has_specular"] is False and "noisy_specular" not in group
    assert group.attrs["scene_hash"] == "hash-b" and group.attrs["spp_levels"] == [1, 4]


def test_attributes_suffice_to_invert_transforms(store):
    """Linear radiance comes back from the store alone: eps and channel order read from its attrs."""
    rng = np.random.default_rng(5)
    linear = rng.uniform(0, 50, (PATCH, PATCH, 3)).astype(np.float32)
    linear[0, 0] = [np.nan, np.inf, -3.0]
    albedo = rng.uniform(0, 1, (PATCH, PATCH, 3)).astype(np.float32)
    albedo[1, 1] = 0.0
    clean, counts = sanitize(linear, "diffuse")
    noisy16, _ = T.to_fp16(T.diffuse_forward(clean, albedo))
    normal = rng.uniform(-1, 1, (PATCH, PATCH, 3)).astype(np.float32)
    depth = rng.uniform(1, 9, (PATCH, PATCH, 1)).astype(np.float32)
    feats16, _ = T.to_fp16(T.features(normal, depth, albedo, np.ones_like(depth)))
    chw = lambda x: np.moveaxis(x, -1, 0)[None]  # noqa: E731
    arrays = {
        "noisy_diffuse": chw(noisy16),
        "features": chw(feats16),
        "ref_diffuse": chw(noisy16),
        "spp": np.array([8]),
        "crop": np.array([0]),
        "origin": np.array([[0, 0]]),
    }
    P.write_scene(store, "val", "one", arrays, {**scene_attrs("one"), "sanitization": {"diffuse": counts}})

    reader = P.PatchReader(store, "val")
    spec = reader.attrs["transform"]
    item = reader[0]
    albedo_channels = [spec["feature_channels"].index(c) for c in ("albedo.R", "albedo.G", "albedo.B")]
    stored_albedo = item["features"][albedo_channels].astype(np.float64)
    back = np.expm1(item["noisy"].astype(np.float64)) * (stored_albedo + spec["eps"])
    expected = np.moveaxis(clean, -1, 0).astype(np.float64)
    # half an FP16 ulp on the stored log value (through expm1) plus the stored albedo's FP16 rounding
    half_ulp = np.spacing(np.abs(item["noisy"]).astype(np.float16)).astype(np.float64) / 2
    amp = stored_albedo + spec["eps"]
    tol = (expected + amp) * np.expm1(half_ulp) * (1 + 2.0**-11) + expected * 2.0**-11 + 1e-6
    assert (np.abs(back - expected) <= tol).all()
    assert P.store_summary(store)["sanitization"]["diffuse"]["nan"] == 1


def test_create_store_is_idempotent_and_refuses_other_transform(store):
    P.create_store(store, dict(ROOT_ATTRS))
    write_synthetic(store, "train", "a", 1)  # a store without scenes pins nothing (the next run takes it over)
    with pytest.raises(P.PatchStoreError, match=r"transform\.eps.*0\.00316.*0\.001"):
        P.create_store(store, {**ROOT_ATTRS, "transform": {**SPEC, "eps": 0.001}})
    with pytest.raises(P.PatchStoreError, match="render_fingerprint"):
        P.create_store(store, {**ROOT_ATTRS, "render_fingerprint": "other"})
    with pytest.raises(P.PatchStoreError, match="'patch_size'"):
        P.create_store(store + "2", {"transform": SPEC})


def test_reader_refuses_mismatching_spec_naming_parameter(store):
    write_synthetic(store, "train", "a", 1)
    with pytest.raises(P.PatchStoreError, match=r"transform spec differs.*\beps\b.*0\.00316.*0\.01"):
        P.PatchReader(store, "train", expect_transform={**SPEC, "eps": 0.01})
    with pytest.raises(P.PatchStoreError, match="feature_channels"):
        P.PatchReader(store, "train", expect_transform={**SPEC, "feature_channels": ["depth"]})


def test_write_scene_refuses_bad_input(store, tmp_path):
    good = synthetic_scene(3)
    bad_shape = {**good, "features": good["features"][:, :6]}
    with pytest.raises(P.PatchStoreError, match=r"features has shape \(6, 6, 128, 128\)"):
        P.write_scene(store, "train", "x", bad_shape, scene_attrs("x"))
    overflow = {**good, "noisy_diffuse": good["noisy_diffuse"].astype(np.float32) * 1e5}
    with pytest.raises(P.PatchStoreError, match="noisy_diffuse has .* not finite in float16"):
        P.write_scene(store, "train", "x", overflow, scene_attrs("x"))
    half_specular = {k: v for k, v in good.items() if k != "ref_specular"}
    with pytest.raises(P.PatchStoreError, match="'ref_specular'"):
        P.write_scene(store, "train", "x", half_specular, scene_attrs("x"))
    with pytest.raises(P.PatchStoreError, match="'scene_hash'"):
        P.write_scene(store, "train", "x", good, {"image_size": [1, 1], "sanitization": {}})
    with pytest.raises(P.PatchStoreError, match="split 'dev'"):
        P.write_scene(store, "dev", "x", good, scene_attrs("x"))
    with pytest.raises(P.PatchStoreError, match="no patch store"):
        P.write_scene(str(tmp_path / "nowhere"), "train", "x", good, scene_attrs("x"))
    assert not P.has_scene(store, "train", "x")


def test_two_processes_write_concurrently(store):
    ctx = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=2, mp_context=ctx) as pool:
        done = list(pool.map(write_synthetic, [store] * 2, ["train"] * 2, ["p", "q"], [11, 12]))
    assert done == ["p", "q"]
    assert P.has_scene(store, "train", "p") and P.has_scene(store, "train", "q")
    reader = P.PatchReader(store, "train", branch="specular")
    assert_rows_match(reader, {"p": synthetic_scene(11), "q": synthetic_scene(12)}, "specular")


def file_states(root: str) -> dict[str, tuple[int, str]]:
    return {
        str(p.relative_to(root)): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
        for p in Path(root).rglob("*")
        if p.is_file()
    }


def test_adding_a_scene_rewrites_nothing_else(store):
    write_synthetic(store, "train", "a", 1)
    write_synthetic(store, "val", "b", 2)
    before = file_states(store)
    time.sleep(0.01)  # so a rewrite would show in mtimes even on coarse clocks
    write_synthetic(store, "train", "c", 3)
    after = file_states(store)
    assert {k: v for k, v in after.items() if not k.startswith("train/c/")} == before
    assert any(k.startswith("train/c/") for k in after)


def test_rewriting_a_scene_replaces_it(store):
    write_synthetic(store, "test", "a", 1)
    write_synthetic(store, "test", "a", 7, specular=False)
    reader = P.PatchReader(store, "test")
    assert reader.scenes == ["a"]
    assert_rows_match(reader, {"a": synthetic_scene(7, specular=False)}, "diffuse")
    assert not [p for p in (Path(store) / P.STAGING).iterdir() if p.is_dir()]


def test_leftover_staging_is_invisible_and_discardable(store):
    """A writer that died before its rename leaves a complete-looking group only under _staging/."""
    staging = Path(store) / P.STAGING / "train.ghost.0123"
    group = zarr.open_group(store=LocalStore(staging), mode="w", attributes={"scene_id": "ghost"})
    group.create_array("features", shape=(2, 7, PATCH, PATCH), dtype="float16", chunks=(1, 7, PATCH, PATCH))
    assert not P.has_scene(store, "train", "ghost")
    assert P.PatchReader(store, "train").scenes == []
    assert P.store_summary(store)["staging_leftovers"] == 1
    assert P.discard_staging(store) == 1
    assert P.store_summary(store)["staging_leftovers"] == 0


WRITER_LOOP = """
import sys, numpy as np
sys.path.insert(0, {tests!r})
from test_patch_store import write_synthetic
for i in range(1000):
    write_synthetic({store!r}, "train", f"s{{i:03d}}", i)
"""


def test_killed_writer_leaves_no_half_scene(store):
    """SIGKILL a process that writes scene after scene: every visible scene is complete and exact."""
    code = WRITER_LOOP.format(tests=str(Path(__file__).parent), store=store)
    proc = subprocess.Popen([sys.executable, "-c", code])
    staging = Path(store) / P.STAGING
    try:
        for _ in range(3000):  # wait (at most ~60 s) until one scene is out and the next is being written
            if P.list_scenes(store, "train") and any(p.name.startswith("train.") for p in staging.iterdir()):
                break
            if proc.poll() is not None:
                pytest.fail(f"writer exited early with {proc.returncode}")
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    visible = P.list_scenes(store, "train")
    assert visible
    expected = {name: synthetic_scene(int(name[1:])) for name in visible}
    assert_rows_match(P.PatchReader(store, "train", branch="specular"), expected, "specular")
    for left in (p for p in staging.iterdir() if p.is_dir()):
        assert left.name.startswith("trash.") or left.name.split(".")[1] not in visible


class CountingStore(LocalStore):
    """LocalStore that tallies the bytes it hands back (instrumentation of the real store)."""

    bytes_read = 0
    calls = 0

    async def get(self, key, prototype, byte_range=None):
        buf = await super().get(key, prototype, byte_range)
        if not key.endswith("zarr.json"):
            CountingStore.calls += 1
            CountingStore.bytes_read += len(buf) if buf is not None else 0
        return buf


def test_reading_one_patch_reads_one_chunk(store):
    scene = synthetic_scene(4, crops=8)  # 16 rows in one shard
    P.write_scene(store, "train", "a", scene, scene_attrs("a"))
    arr = zarr.open_array(store=CountingStore(store, read_only=True), path="train/a/features", mode="r")
    assert arr.chunks == (1, 7, PATCH, PATCH) and arr.shards == (16, 7, PATCH, PATCH)
    codec = arr.metadata.codecs[0].codecs[-1]
    assert codec.cname.value == "zstd" and codec.clevel == 3 and codec.shuffle.value == "bitshuffle"
    CountingStore.calls = CountingStore.bytes_read = 0
    np.testing.assert_array_equal(arr[5], scene["features"][5])
    shard_bytes = sum(f.stat().st_size for f in (Path(store) / "train/a/features/c").rglob("*") if f.is_file())
    index_bytes = 16 * 16 + 4  # (offset, length) per chunk + crc32c
    assert CountingStore.calls == 2  # the shard index, then the chunk's byte range
    assert CountingStore.bytes_read <= shard_bytes / 16 * 1.5 + index_bytes


def test_reader_pickles_for_worker_processes(store):
    import pickle

    write_synthetic(store, "train", "a", 1)
    reader = P.PatchReader(store, "train")
    reader[0]
    clone = pickle.loads(pickle.dumps(reader))
    np.testing.assert_array_equal(clone[3]["noisy"], reader[3]["noisy"])
    with pytest.raises(IndexError):
        reader[len(reader)]


def test_store_summary_counts(store):
    write_synthetic(store, "train", "a", 1)
    write_synthetic(store, "train", "b", 2, specular=False)
    write_synthetic(store, "test", "c", 3)
    summary = P.store_summary(store)
    train = summary["splits"]["train"]
    assert train["scenes"] == ["a", "b"] and train["rows"] == {"diffuse": 12, "specular": 6}
    assert train["crops"] == 6 and train["rows_per_spp"] == {1: 6, 4: 6}
    lo, hi = train["ranges"]["features"]
    assert 0.0 <= lo < 0.01 and 0.99 < hi <= 1.0
    assert summary["splits"]["test"]["rows"]["specular"] == 6
    assert summary["sanitization"] == {"diffuse": {"nan": 6, "posinf": 3}}


def test_a_store_of_an_older_format_is_refused_with_what_to_do(tmp_path):
    """format_version 1 promised references shared per image crop; this code writes one per row."""
    path = tmp_path / "old.zarr"
    assert not P.exists(path)
    P.create_store(path, ROOT_ATTRS)
    assert P.exists(path) and P.FORMAT_VERSION == 2
    zarr.open_group(store=LocalStore(path), mode="r+").attrs["format_version"] = 1
    for opening in (
        lambda: P.PatchReader(path, "train"),
        lambda: P.fingerprint(path),
        lambda: P.create_store(path, ROOT_ATTRS),
    ):
        with pytest.raises(
            P.PatchStoreError,
            match=r"format_version 1, this code reads 2; written by an older "
            r"admc: move it away .* run `admc-pipe dataset`",
        ):
            opening()


def test_noise_maps_come_per_branch_and_join_the_features_only_when_asked(store):
    with_noise = synthetic_scene(5)
    n = len(with_noise["spp"])
    rng = np.random.default_rng(5)
    for branch in ("diffuse", "specular"):
        with_noise[f"noise_{branch}"] = rng.uniform(0, 1, (n, 1, PATCH, PATCH)).astype(np.float16)
    P.write_scene(store, "train", "noisy-a", with_noise, scene_attrs("noisy-a"))
    assert P.has_noise_maps(store, "train", "noisy-a")
    for branch in ("diffuse", "specular"):
        plain, read = (
            P.PatchReader(store, "train", branch=branch),
            P.PatchReader(store, "train", branch=branch, noise=True),
        )
        assert plain[1]["features"].shape == (7, PATCH, PATCH)
        assert read[1]["features"].shape == (8, PATCH, PATCH)
        np.testing.assert_array_equal(read[1]["features"][:7], plain[1]["features"])
        np.testing.assert_array_equal(read[1]["features"][7], with_noise[f"noise_{branch}"][1, 0].astype(np.float32))
    assert "noise_diffuse" in P.store_summary(store)["splits"]["train"]["ranges"]

    only_diffuse = {k: v for k, v in with_noise.items() if k != "noise_specular"}
    with pytest.raises(P.PatchStoreError, match="missing array 'noise_specular'"):
        P.write_scene(store, "train", "x", only_diffuse, scene_attrs("x"))
    no_specular = {k: v for k, v in synthetic_scene(6, specular=False).items()}
    no_specular.update({k: with_noise[k] for k in ("noise_diffuse", "noise_specular")})
    with pytest.raises(P.PatchStoreError, match="noise_specular given for a scene without specular arrays"):
        P.write_scene(store, "train", "x", no_specular, scene_attrs("x"))


def test_a_store_without_noise_maps_is_refused_for_noise_input_naming_it_and_what_to_run(store):
    write_synthetic(store, "train", "older", seed=7)  # tiled without noise maps
    n = len(P.PatchReader(store, "train"))
    assert n > 0 and not P.has_noise_maps(store, "train", "older")
    attrs = zarr.open_group(store=LocalStore(Path(store) / "train" / "older"), mode="r").attrs
    assert "has_noise" not in attrs  # a scene without them has the attributes it always had
    with pytest.raises(
        P.PatchStoreError,
        match=rf"patch store {store}: scene train/older has no noise maps.*"
        r"run `admc-pipe dataset` with this config and --set "
        r"model.noise_input=true",
    ):
        P.PatchReader(store, "train", noise=True)
