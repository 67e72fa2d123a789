"""Render + tile end to end: the patch store holds exactly what the EXRs say, incrementally."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from admc.errors import ConfigError, StageError
from admc.model import transforms as tf
from admc.pipeline.config import load_config
from admc.pipeline.tiler import tile
from admc.pipeline.tiler.report import contact_sheet_path
from admc.pipeline.stages.dataset import build_dataset
from admc.stores import exr, patches

ADMC = str(Path(sys.executable).parent / "admc-pipe")


def tiny_overrides(n_scenes):
    return [
        "run.scheduler=sync",
        "render.resolution=[64, 64]",
        "render.spp=[2, 4]",
        "render.reference_spp=16",
        "corpus.families=['room', 'tabletop']",
        f"corpus.n_scenes={n_scenes}",
        "tile.patch_size=32",
        "tile.crops_per_scene=3",
        "tile.split=[0.6, 0.2, 0.2]",
    ]


def tiny(workdir, n_scenes):
    return load_config(None, [f"run.workdir='{workdir}'", *tiny_overrides(n_scenes)])


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from admc.pipeline.render.variants import use_variant

    use_variant("auto")
    workdir = tmp_path_factory.mktemp("dataset")
    return workdir, build_dataset(tiny(workdir, 3), progress=False)


def test_store_rows_equal_the_transformed_exr_crops(built):
    workdir, result = built
    assert result.executed == 3 * 3 + 3
    for summary in result.tiles:
        reader_rows = 0
        group = f"{summary['split']}/{summary['scene_id']}"
        scene = patches.PatchReader(result.store, summary["split"])
        rows = [i for i in range(len(scene)) if scene.locate(i)[0] == summary["scene_id"]]
        for i in rows:
            row = scene[i]
            y, x = _origin(result.store, group, scene.locate(i)[1])
            layers = exr.read_exr(result.renders_dir / summary["scene_id"] / f"spp{row['spp']:04d}.exr")
            crop = (slice(y, y + 32), slice(x, x + 32))
            want = tf.diffuse_forward(layers["diffuse"], layers["albedo"])[crop].transpose(2, 0, 1)
            np.testing.assert_array_equal(row["noisy"], want.astype(np.float16).astype(np.float32))
            feats = tf.features(layers["normal"], layers["depth"], layers["albedo"], layers["coverage"])
            np.testing.assert_array_equal(row["features"], feats[crop].transpose(2, 0, 1).astype(np.float16))
            reader_rows += 1
        crops = 4 if summary["split"] == "val" else 3  # val: the 2x2 grid of 32-pixel crops that covers 64x64
        assert reader_rows == summary["rows"] == crops * 2


def _origin(store, group, row):
    import zarr

    g = zarr.open_group(str(store / group), mode="r")
    return g["origin"][int(g["crop"][row])]


def test_store_attributes_invert_the_reference(built):
    workdir, result = built
    import zarr

    root = zarr.open_group(str(result.store), mode="r")
    assert root.attrs["transform"] == tf.transform_spec()
    assert root.attrs["feature_channels"] == list(tf.FEATURE_CHANNELS)
    summary = result.tiles[0]
    group = root[f"{summary['split']}/{summary['scene_id']}"]
    renders = {t.key for t in result.tasks if t.stage == "render"}
    assert set(group.attrs["render_keys"].values()) <= renders and len(group.attrs["render_keys"]) == 3
    reference = exr.read_exr(result.renders_dir / summary["scene_id"] / "reference.exr")
    for row in (0, group["spp"].shape[0] - 1):
        y, x = group["origin"][int(group["crop"][row])]
        stored = group["ref_diffuse"][int(group["crop"][row])].astype(np.float32).transpose(1, 2, 0)
        albedo = group["features"][row][4:7].astype(np.float32).transpose(1, 2, 0)  # the row's own albedo
        back = tf.diffuse_inverse(stored, albedo)
        want = reference["diffuse"][y : y + 32, x : x + 32]
        np.testing.assert_allclose(back, want, rtol=2e-3, atol=2e-3)


def test_rerun_does_nothing_and_a_new_scene_tiles_only_itself(built):
    workdir, result = built
    again = build_dataset(tiny(workdir, 3), progress=False)
    assert again.executed == 0
    before = {p: p.stat().st_mtime_ns for p in result.store.rglob("*") if p.is_file()}
    grown = build_dataset(tiny(workdir, 4), progress=False)
    assert grown.executed == 3 + 1, "one new scene: its 3 renders and its tile task"
    after = {p: p.stat().st_mtime_ns for p in result.store.rglob("*") if p.is_file()}
    assert all(after[p] == t for p, t in before.items()), "existing scenes must not be rewritten"
    assert sum(len(patches.list_scenes(result.store, s)) for s in patches.SPLITS) == 4


def test_deleted_store_is_rebuilt_from_cached_renders(tmp_path, variant):
    first = build_dataset(tiny(tmp_path, 1), progress=False)
    import shutil

    shutil.rmtree(first.store)
    again = build_dataset(tiny(tmp_path, 1), progress=False)
    assert again.executed == 1, "only the tile task reruns; renders stay cached"
    assert sum(len(patches.list_scenes(again.store, s)) for s in patches.SPLITS) == 1


def _fake_render(folder: Path, layers: dict, precision="float") -> Path:
    folder.mkdir(parents=True)
    exr.write_exr(folder / "render.exr", layers, precision=precision)
    return folder


def _layers(rng, size, specular=True, poison=False):
    h = w = size
    layers = {
        "diffuse": rng.random((h, w, 3), dtype=np.float32),
        "albedo": rng.random((h, w, 3), dtype=np.float32),
        "normal": rng.uniform(-1, 1, (h, w, 3)).astype(np.float32),
        "depth": rng.uniform(1, 5, (h, w, 1)).astype(np.float32),
        "coverage": np.ones((h, w, 1), np.float32),
        "diffuse_var": rng.random((h, w, 3), dtype=np.float32) * 0.01,
    }
    if specular:
        layers["specular"] = rng.random((h, w, 3), dtype=np.float32)
        layers["specular_var"] = rng.random((h, w, 3), dtype=np.float32) * 0.01
    if poison:
        layers["diffuse"][0, 0] = np.nan
        layers["diffuse"][1, 1] = np.inf
        layers["diffuse"][2, 2] = 1e9
        layers["normal"][3, 3] = np.nan
        layers["depth"][4, 4] = np.inf
        layers["coverage"][5:, :4] = 0.0  # environment-only pixels
        if specular:
            layers["specular"][6, 6] = -np.inf
    return layers


def _store(tmp_path):
    store = tmp_path / "p.zarr"
    patches.create_store(store, {"transform": tf.transform_spec(), "patch_size": 16})
    return store


@pytest.mark.parametrize("specular", [True, False])
def test_nan_inf_and_huge_pixels_are_handled_and_reported(tmp_path, specular):
    rng = np.random.default_rng(1)
    inputs = {
        "reference": _fake_render(tmp_path / "ref", _layers(rng, 32, specular, poison=True)),
        "spp0004": _fake_render(tmp_path / "n4", _layers(rng, 32, specular, poison=True)),
    }
    store = _store(tmp_path)
    out = tile.tile_scene(
        tmp_path,
        inputs,
        store=str(store),
        split="train",
        scene_id="poisoned",
        scene_hash="ab" * 32,
        patch_size=16,
        crops_per_scene=4,
        candidates_per_crop=4,
        seed=0,
    )
    # counts are per value: each poisoned pixel has 3 channels
    assert out["sanitized"]["reference/diffuse"]["nan"] == 3
    assert out["sanitized"]["reference/diffuse"]["posinf"] == 3
    assert out["sanitized"]["reference/diffuse"]["above_max"] == 3  # 1e9 clamped to the FP16-safe maximum
    assert out["sanitized"]["spp0004/normal"]["nan"] == 3
    assert out["sanitized"]["spp0004/depth"]["posinf"] == 1
    if specular:
        assert out["sanitized"]["spp0004/specular"]["neginf"] == 3
    import zarr

    group = zarr.open_group(str(store / "train" / "poisoned"), mode="r")
    for name in group.array_keys():
        assert np.isfinite(group[name][...].astype(np.float32)).all(), name
    assert ("noisy_specular" in group) == specular
    reader = patches.PatchReader(store, "train", branch="specular")
    assert len(reader) == (4 if specular else 0), "a scene without specular gives no specular patches"


def test_split_is_by_scene_and_stable():
    ids = [f"room-{i:04d}" for i in range(400)]
    splits = [tile.split_of(s, (0.8, 0.1, 0.1), 0) for s in ids]
    assert splits == [tile.split_of(s, (0.8, 0.1, 0.1), 0) for s in ids]
    share = {s: splits.count(s) / len(ids) for s in patches.SPLITS}
    assert 0.72 < share["train"] < 0.88 and 0.05 < share["val"] < 0.15 and 0.05 < share["test"] < 0.15


@pytest.mark.parametrize(
    "n, fractions, counts",
    [
        (20, (0.6, 0.15, 0.25), [12, 3, 5]),
        (24, (0.6, 0.15, 0.25), [14, 4, 6]),
        (8, (0.8, 0.1, 0.1), [6, 1, 1]),
        (3, (0.6, 0.15, 0.25), [1, 1, 1]),  # every nonzero fraction gets a scene where n allows
        (2, (0.6, 0.15, 0.25), [1, 0, 1]),  # ... and train keeps its one
        (5, (1.0, 0.0, 0.0), [5, 0, 0]),
    ],
)
def test_exact_split_counts_are_the_shares_rounded(n, fractions, counts):
    assert tile.exact_counts(n, fractions) == counts


def test_exact_split_ranks_the_hash_and_cuts_it_at_the_shares():
    """20 frames whose hash alone gives one val frame get 12 / 3 / 5, keeping the hash's order: every
    train frame draws below every val frame, every val frame below every test frame."""
    ids = [f"xml-interior-2-{i:03d}" for i in range(20)]
    by_hash = tile.assign_splits(ids, (0.6, 0.15, 0.25), 17)
    assert [list(by_hash.values()).count(s) for s in patches.SPLITS] == [14, 1, 5]
    exact = tile.assign_splits(ids, (0.6, 0.15, 0.25), 17, exact=True)
    assert [list(exact.values()).count(s) for s in patches.SPLITS] == [12, 3, 5]
    draws = {s: [tile._draw(i, 17) for i in ids if exact[i] == s] for s in patches.SPLITS}
    assert max(draws["train"]) < min(draws["val"]) and max(draws["val"]) < min(draws["test"])
    assert tile.assign_splits(ids[::-1], (0.6, 0.15, 0.25), 17, exact=True) == exact
    assert by_hash == {i: tile.split_of(i, (0.6, 0.15, 0.25), 17) for i in ids}


def test_a_store_that_holds_a_moved_scene_is_refused(tmp_path, variant):
    """With exact splits a fourth scene moves room-0000 from val to train: tiling on into the same store
    would train on a frame it validated on, so the store is refused with the scene named."""
    exact = ["tile.split_exact=true", "tile.crops_per_scene=1"]
    cfg = load_config(None, [f"run.workdir='{tmp_path}'", *tiny_overrides(3), *exact])
    build_dataset(cfg, progress=False)
    assert patches.list_scenes(tmp_path / cfg.tile.store, "val") == ["room-0000"]
    grown = load_config(None, [f"run.workdir='{tmp_path}'", *tiny_overrides(4), *exact])
    with pytest.raises(StageError, match=r"holds room-0000 in its val split, and tile.split now puts it in train"):
        build_dataset(grown, progress=False)
    assert patches.list_scenes(tmp_path / cfg.tile.store, "val") == ["room-0000"]  # nothing rewritten
    moved = load_config(None, [f"run.workdir='{tmp_path}'", *tiny_overrides(4), *exact, "tile.store='grown.zarr'"])
    assert patches.list_scenes(build_dataset(moved, progress=False).store, "train").count("room-0000") == 1


def test_partner_targets_are_raw_where_converged_and_cleaned_where_heavy_tailed():
    """The raw reference's weight falls from 1 to 0 as its relative standard deviation (7x7 mean of its
    variance layer over the 7x7 mean value) goes through tile.UNCONVERGED_REL_STD; its cleaned twin fills in."""
    low, high = tile.UNCONVERGED_REL_STD
    rel_std = np.repeat([0.5 * low, low, (low + high) / 2, high, 2 * high], 8).astype(
        np.float32
    )  # 5 bands of 8 columns
    value = np.full((20, 40, 3), 2.0, np.float32)
    raw = {
        "diffuse": value,
        "diffuse_var": np.broadcast_to((rel_std * 2.0) ** 2, (20, 40))[..., None] * np.ones(3, np.float32),
    }
    cleaned = {"diffuse": np.full_like(value, 3.0)}
    weight = tile.converged_share(raw, "diffuse")[10, 4::8, 0]  # each band's centre column: its 7x7 window within
    np.testing.assert_allclose(weight, [1.0, 1.0, 0.5, 0.0, 0.0], atol=1e-5)
    target = tile.partner_references(raw, cleaned)
    assert set(target) == {"diffuse"}
    np.testing.assert_allclose(target["diffuse"][10, 4::8, 0], 2.0 * weight + 3.0 * (1 - weight), rtol=1e-6)


def test_crops_favour_noisy_regions():
    score = np.zeros((64, 64))
    score[:, 32:] = 1.0  # the right half is noisy
    origins = tile.choose_crops(score, 200 // 10, 16, 8, np.random.default_rng(0))
    right = (origins[:, 1] >= 24).mean()
    assert right > 0.7


@pytest.mark.parametrize("height, width, patch", [(256, 256, 128), (160, 200, 128), (64, 64, 32), (128, 131, 128)])
def test_val_crops_cover_the_whole_frame_once_per_grid_cell(height, width, patch):
    origins = tile.grid_origins(height, width, patch)
    covered = np.zeros((height, width), dtype=int)
    for y, x in origins:
        assert 0 <= y <= height - patch and 0 <= x <= width - patch
        covered[y : y + patch, x : x + patch] += 1
    assert covered.min() >= 1 and len(origins) == -(-height // patch) * -(-width // patch)
    if height % patch == 0 and width % patch == 0:
        assert covered.max() == 1  # an exact tiling: every pixel scored once


def test_image_smaller_than_patch_is_a_clear_error():
    with pytest.raises(ValueError, match="smaller than the 128x128"):
        tile.choose_crops(np.ones((64, 64)), 1, 128, 4, np.random.default_rng(0))


def test_cli_summary_prints_counts_and_writes_contact_sheet(built):
    workdir, result = built
    args = [
        "--set",
        f"run.workdir='{workdir}'",
        "--set",
        "tile.patch_size=32",
        "--set",
        "tile.crops_per_scene=3",
        "--set",
        "tile.split=[0.6, 0.2, 0.2]",
        "--set",
        "render.spp=[2, 4]",
        "--set",
        "render.reference_spp=16",
    ]
    out = subprocess.run([ADMC, "dataset", "--summary", *args], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "train" in out.stdout and "sanitized values" in out.stdout
    sheet = contact_sheet_path(workdir, result.store)
    assert str(sheet) in out.stdout
    from PIL import Image

    image = Image.open(sheet)
    assert image.size[0] == 4 * 32 + 3 * 4 and image.size[1] >= 32


def test_user_xml_scenes_become_a_domain_set(tmp_path, variant):
    """A folder of the user's Mitsuba XML scenes renders and tiles like the procedural corpus."""
    from test_scenes import write_kitchen_scene

    scenes = write_kitchen_scene(tmp_path / "my_scenes").parent
    cfg = load_config(
        None,
        [
            f"run.workdir='{tmp_path / 'work'}'",
            "run.scheduler=sync",
            "render.spp=[2]",
            "render.reference_spp=8",
            "render.resolution=[32, 32]",
            "corpus.n_scenes=0",
            f"corpus.xml_dirs=['{scenes}']",
            "tile.patch_size=32",
            "tile.crops_per_scene=2",
            "tile.split=[1.0, 0.0, 0.0]",
        ],
    )
    result = build_dataset(cfg, progress=False)
    assert [s.scene_id for s in result.scenes] == ["xml-kitchen"]
    assert patches.list_scenes(result.store, "train") == ["xml-kitchen"]
    reader = patches.PatchReader(result.store, "train", branch="specular")
    assert len(reader) == 2, "the rough plastic sphere makes it a specular scene"


def test_tiled_scenes_match_the_documented_layout(built):
    """One reference entry per row, as patches.LAYOUT says: crop is the identity and n_crops == n_rows."""
    import zarr

    workdir, result = built
    root = zarr.open_group(str(result.store), mode="r")
    for summary in result.tiles:
        group = root[f"{summary['split']}/{summary['scene_id']}"]
        n = group["spp"].shape[0]
        assert group.attrs["n_crops"] == group.attrs["n_rows"] == n == group["origin"].shape[0]
        np.testing.assert_array_equal(group["crop"][:], np.arange(n))
        assert group["ref_diffuse"].shape[0] == n


def test_scenes_with_constructs_tile_into_the_store(tmp_path, variant):
    """A broadened corpus (configs/broad.toml) names a scene by its constructs, "room-1000000+grate": the
    store takes that name (it refused the "+" once, so no construct scene ever reached training)."""
    cfg = load_config(
        None,
        [
            f"run.workdir='{tmp_path}'",
            "run.scheduler=sync",
            "render.resolution=[32, 32]",
            "render.spp=[2]",
            "render.reference_spp=4",
            "corpus.families=['room']",
            "corpus.n_scenes=2",
            "corpus.construct_chance=1.0",
            "tile.patch_size=32",
            "tile.crops_per_scene=1",
            "tile.split=[1.0, 0.0, 0.0]",
        ],
    )
    result = build_dataset(cfg, progress=False)
    names = [s.scene_id for s in result.scenes]
    assert all("+" in name for name in names), names
    assert patches.list_scenes(result.store, "train") == sorted(names)


def test_noise_maps_are_tiled_when_the_config_asks_and_kept_across_runs_without_them(tmp_path):
    """tile.noise_maps (or model.noise_input) stores each branch's noise map per row: the render's variance
    through transforms.*_noise, cropped like every row. A run without them into the same store re-tiles
    the scenes without them; the next run that asks re-tiles them back from the cached renders."""
    from admc.pipeline.render.variants import use_variant

    use_variant("auto")
    plain = tiny(tmp_path, 2)
    noisy = load_config(
        None,
        [
            f"run.workdir='{tmp_path}'",
            "run.scheduler=sync",
            "render.resolution=[64, 64]",
            "render.spp=[2, 4]",
            "render.reference_spp=16",
            "corpus.families=['room', 'tabletop']",
            "corpus.n_scenes=2",
            "tile.patch_size=32",
            "tile.crops_per_scene=3",
            "tile.split=[0.6, 0.2, 0.2]",
            "model.noise_input=true",
        ],
    )
    result = build_dataset(noisy, progress=False)
    for summary in result.tiles:
        assert summary["has_noise"] and patches.has_noise_maps(result.store, summary["split"], summary["scene_id"])
        for branch in ("diffuse", "specular"):
            plain_rows = patches.PatchReader(result.store, summary["split"], branch=branch)
            with_noise = patches.PatchReader(result.store, summary["split"], branch=branch, noise=True)
            rows = [i for i in range(len(plain_rows)) if plain_rows.locate(i)[0] == summary["scene_id"]]
            for i in rows:
                row, features = plain_rows[i], with_noise[i]["features"]
                y, x = _origin(result.store, f"{summary['split']}/{summary['scene_id']}", plain_rows.locate(i)[1])
                layers = exr.read_exr(result.renders_dir / summary["scene_id"] / f"spp{row['spp']:04d}.exr")
                noise = (
                    tf.diffuse_noise(layers["diffuse_var"], layers["diffuse"], layers["albedo"])
                    if branch == "diffuse"
                    else tf.specular_noise(layers["specular_var"], layers["specular"])
                )
                np.testing.assert_array_equal(features[:-1], row["features"])
                np.testing.assert_array_equal(
                    features[-1:],
                    noise[y : y + 32, x : x + 32].transpose(2, 0, 1).astype(np.float16).astype(np.float32),
                )
    assert len(result.tiles) == 2 and any(
        len(patches.PatchReader(result.store, s["split"], noise=True)) for s in result.tiles
    )

    again = build_dataset(plain, progress=False)  # renders cached; the tiles without noise maps run
    assert again.executed == 2
    assert not any(patches.has_noise_maps(again.store, s["split"], s["scene_id"]) for s in again.tiles)
    back = build_dataset(noisy, progress=False)  # its tile tasks are cached, but the scenes lost their maps
    assert back.executed == 2
    assert all(patches.has_noise_maps(back.store, s["split"], s["scene_id"]) for s in back.tiles)
    assert build_dataset(noisy, progress=False).executed == 0


def test_noise_maps_of_poisoned_variance_are_finite(tmp_path):
    rng = np.random.default_rng(2)
    noisy = _layers(rng, 32, True, poison=True)
    noisy["diffuse_var"][7, 7] = [np.nan, np.inf, -1.0]
    noisy["specular_var"][8, 8] = [np.inf, 1e30, -np.inf]
    inputs = {
        "reference": _fake_render(tmp_path / "ref", _layers(rng, 32, True)),
        "spp0004": _fake_render(tmp_path / "n4", noisy),
    }
    store = _store(tmp_path)
    out = tile.tile_scene(
        tmp_path,
        inputs,
        store=str(store),
        split="train",
        scene_id="poisoned",
        scene_hash="ab" * 32,
        patch_size=16,
        crops_per_scene=4,
        candidates_per_crop=4,
        seed=0,
        noise_maps=True,
    )
    assert out["has_noise"]
    import zarr

    group = zarr.open_group(str(store / "train" / "poisoned"), mode="r")
    for name in ("noise_diffuse", "noise_specular"):
        values = group[name][...].astype(np.float32)
        assert values.shape == (4, 1, 16, 16) and np.isfinite(values).all() and (values >= 0).all()


def test_val_references_are_rendered_at_val_reference_spp_by_render_and_dataset_alike(tmp_path):
    """render.val_reference_spp: the val scene's reference (what selection scores against) is a render of its own
    at that spp, the train scene's stays at reference_spp; `admc-pipe render` renders the same, so tiling after
    it renders nothing; the val rows' targets are that reference's crops, and eval of the val split scores it."""
    from admc.pipeline.render.variants import use_variant
    from admc.pipeline.stages.evaluate import scoring_config
    from admc.pipeline.stages.render import render_corpus

    use_variant("auto")
    cfg = load_config(
        None,
        [
            f"run.workdir='{tmp_path}'",
            *tiny_overrides(2),
            "tile.split=[0.5, 0.5, 0.0]",
            "tile.seed=1",
            "render.val_reference_spp=24",
        ],
    )  # one of each
    rendered = render_corpus(cfg, progress=False)
    result = build_dataset(cfg, progress=False)
    assert result.executed == 2  # the two tiles: every render was already there
    assert {s["split"] for s in result.tiles} == {"train", "val"}
    for summary in result.tiles:
        sidecar = json.loads((rendered.renders_dir / summary["scene_id"] / "reference.json").read_text())
        assert sidecar["spp"] == (24 if summary["split"] == "val" else 16)
    val_id = next(s["scene_id"] for s in result.tiles if s["split"] == "val")
    reference = tile._clean(exr.read_exr(result.renders_dir / val_id / "reference.exr"), {}, "reference")
    rows = patches.PatchReader(result.store, "val", branch="diffuse")
    y, x = _origin(result.store, f"val/{val_id}", rows.locate(0)[1])
    layers = exr.read_exr(result.renders_dir / val_id / f"spp{rows[0]['spp']:04d}.exr")
    want = tf.diffuse_forward(reference["diffuse"], layers["albedo"])[y : y + 32, x : x + 32].transpose(2, 0, 1)
    np.testing.assert_array_equal(rows[0]["reference"], want.astype(np.float16).astype(np.float32))
    val_eval = load_config(
        None, [f"run.workdir='{tmp_path}'", *tiny_overrides(2), "render.val_reference_spp=24", "eval.split=val"]
    )
    assert scoring_config(val_eval).render.reference_spp == 24
    assert scoring_config(load_config(None, ["render.val_reference_spp=128"])).render.reference_spp == 384  # test split
    with pytest.raises(ConfigError, match="val_reference_spp"):
        load_config(None, ["render.val_reference_spp=4"])


def test_clean_targets_are_oidn_on_the_reference_and_need_a_store_of_their_own(tmp_path):
    """tile.clean_targets: each train row's target is OIDN's per-branch output on the sanitised reference (the
    refiner's base function at `high`), transformed as the raw reference would be; noisy rows and features
    are untouched. Train rows keep the raw reference beside it where it has converged (what OIDN's fine-tune tries
    too: tile.partner_references); val rows keep
    only the raw reference (OIDN's output would favour OIDN in validation). The store records it, so a store
    tiled on raw references refuses the clean config."""
    from admc.model.inference.oidn_base import oidn_bases
    from admc.pipeline.render.variants import use_variant

    use_variant("auto")
    overrides = [
        f"run.workdir='{tmp_path / 'raw'}'",
        *tiny_overrides(2),
        "tile.split=[0.5, 0.5, 0.0]",
        "tile.seed=1",
    ]  # one of each
    raw = build_dataset(load_config(None, overrides), progress=False)
    clean_cfg = load_config(None, [*overrides, "tile.clean_targets=true", "tile.store=clean.zarr"])
    clean = build_dataset(clean_cfg, progress=False)
    assert clean.executed == 2 and all(s["split"] for s in clean.tiles)  # renders cached: only the tiles ran
    assert {s["split"] for s in clean.tiles} == {"train", "val"}
    for summary in clean.tiles:
        split, scene_id = summary["split"], summary["scene_id"]
        reference = tile._clean(exr.read_exr(clean.renders_dir / scene_id / "reference.exr"), {}, "reference")
        bases = oidn_bases(reference, "oidn")
        for branch in ("diffuse", "specular"):
            clean_rows = patches.PatchReader(clean.store, split, branch=branch)
            raw_rows = patches.PatchReader(raw.store, split, branch=branch)
            assert clean_rows.holds_raw_references == (split == "train") and not raw_rows.holds_raw_references
            if split == "train":
                clean_rows = clean_rows.with_raw_references()
            else:
                with pytest.raises(patches.PatchStoreError, match="keeps no raw references"):
                    clean_rows.with_raw_references()
            rows = [i for i in range(len(clean_rows)) if clean_rows.locate(i)[0] == scene_id]
            for i in rows:
                row, raw_row = clean_rows[i], raw_rows[i]
                np.testing.assert_array_equal(row["noisy"], raw_row["noisy"])
                np.testing.assert_array_equal(row["features"], raw_row["features"])
                if split == "val":
                    np.testing.assert_array_equal(row["reference"], raw_row["reference"])
                    continue
                y, x = _origin(clean.store, f"{split}/{scene_id}", clean_rows.locate(i)[1])
                layers = exr.read_exr(clean.renders_dir / scene_id / f"spp{row['spp']:04d}.exr")
                want = (
                    tf.diffuse_forward(bases["diffuse"], layers["albedo"])
                    if branch == "diffuse"
                    else tf.specular_forward(bases["specular"])
                )[y : y + 32, x : x + 32].transpose(2, 0, 1)
                np.testing.assert_array_equal(row["reference"], want.astype(np.float16).astype(np.float32))
                assert not np.array_equal(row["reference"], raw_row["reference"])
                partner = tile.partner_references(reference, bases)[branch]
                want_raw = (
                    tf.diffuse_forward(partner, layers["albedo"])
                    if branch == "diffuse"
                    else tf.specular_forward(partner)
                )[y : y + 32, x : x + 32].transpose(2, 0, 1)
                np.testing.assert_array_equal(row["raw_reference"], want_raw.astype(np.float16).astype(np.float32))
    mixed = load_config(None, [*overrides, "tile.clean_targets=true"])
    with pytest.raises(patches.PatchStoreError, match="clean_targets"):
        build_dataset(mixed, progress=False)  # the raw store (patches.zarr) is refused, naming the key
