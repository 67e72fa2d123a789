"""admc+oidn: a CFM generator that corrects Intel Open Image Denoise's output (model.base "oidn" or "oidn-fast").

Real OIDN (pyoidn), real renders, a real patch store and real training steps at tiny sizes.
"""

import dataclasses

import numpy as np
import pytest
import torch

from admc.common.buffers import sanitize
from admc.common.layout import BASE_QUALITIES
from admc.model import transforms as tf
from admc.model.inference.denoiser import FullImageDenoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.oidn_base import oidn_bases
from admc.model.nets.backbones import build_generator
from admc.model.nets.settings import ModelSettings
from admc.model.training.trainer import train
from admc.pipeline.config import ConfigError, load_config
from admc.pipeline.stages.dataset import build_dataset
from admc.stores import exr, patches
from admc.stores.checkpoints import read_networks
from admc.stores.patches import PatchReader, PatchStoreError
from conftest import preset, tiny_store_overrides

TINY = dict(channels=8, blocks=1, cond_channels=8, encoder_channels=8, input_skip=True)


def refiner(backbone="residual", base="oidn"):
    torch.manual_seed(0)
    return build_generator(ModelSettings(**TINY, backbone=backbone, base=base))


@pytest.mark.parametrize("backbone", ["residual", "unet"])
def test_an_untrained_refiner_returns_its_base_exactly(backbone):
    noisy, feats, base = torch.rand(2, 3, 40, 24), torch.rand(2, 7, 40, 24), torch.rand(2, 3, 40, 24) * 5
    assert torch.equal(refiner(backbone)(noisy, feats, base), base)


def test_the_refiner_sees_the_noisy_input_and_learns_from_the_first_step():
    g = refiner()
    noisy, feats, base = torch.rand(1, 3, 16, 16), torch.rand(1, 7, 16, 16), torch.rand(1, 3, 16, 16)
    g(noisy, feats, base).sub(base + 0.1).abs().mean().backward()
    last = g.tail[-2].weight
    assert id(last) in {id(p) for p in g.parameter_groups()["body"]}  # learns from step 0 with the body
    assert last.grad.abs().sum() > 0
    with torch.no_grad():
        last.normal_(0.0, 0.1)
        other = noisy.clone()
        other[..., 8, 8] += 1.0  # a different noisy input changes the output through the encoder
        assert not torch.equal(g(noisy, feats, base), g(other, feats, base))


def test_base_is_required_exactly_when_the_generator_refines():
    noisy, feats = torch.rand(1, 3, 8, 8), torch.rand(1, 7, 8, 8)
    with pytest.raises(ValueError, match="base image"):
        refiner()(noisy, feats)
    with pytest.raises(ValueError, match="takes no base"):
        build_generator(ModelSettings(**TINY))(noisy, feats, noisy)
    with pytest.raises(ValueError, match="base"):
        ModelSettings(mode="none", base="oidn").check()


def test_config_refuses_a_refiner_without_stored_bases(tmp_path):
    with pytest.raises(ConfigError, match="tile.oidn_base"):
        load_config(None, [f"run.workdir='{tmp_path}'", "model.base='oidn'", "tile.oidn_base=false"])
    with pytest.raises(ConfigError, match="model.base"):
        load_config(None, [f"run.workdir='{tmp_path}'", "model.base='median'"])
    with pytest.raises(
        ConfigError,
        match=r"tile.refiner_base': is 'oidn-fast', but model.base = 'oidn' trains on the "
        r"bases of 'oidn' \(OIDN 'high'; the store's: diffuse high, specular fast\): "
        r"set model.base = 'oidn-fast'",
    ):
        load_config(None, [f"run.workdir='{tmp_path}'", "model.base='oidn'", "tile.refiner_base='oidn-fast'"])
    with pytest.raises(ConfigError, match="tile.refiner_base': must be one of oidn, oidn-fast, got 'best'"):
        load_config(None, [f"run.workdir='{tmp_path}'", "tile.refiner_base='best'"])


@pytest.fixture(scope="module")
def store_with_bases(tmp_path_factory, variant):
    workdir = tmp_path_factory.mktemp("bases")
    cfg = load_config(None, tiny_store_overrides(workdir, 64, 32))
    return cfg, build_dataset(cfg, progress=False).store


def test_tiling_stores_oidn_of_the_whole_image_per_row(store_with_bases):
    cfg, store = store_with_bases
    base = cfg.tile.refiner_base
    reader = PatchReader(store, "train", branch="diffuse", base=base)
    scene, row = reader.locate(0)
    item = reader[0]
    group = patches.format._open_root(store)[f"train/{scene}"]
    assert group.attrs["has_base"] and group.attrs["base"]["method"] == "oidn"
    assert group.attrs["base"]["quality"] == BASE_QUALITIES[base]
    y, x = (int(v) for v in group["origin"][row])
    spp = item["spp"]
    layers = {
        name: sanitize(a, name)[0]
        for name, a in exr.read_exr(cfg.workdir_path("renders") / scene / f"spp{spp:04d}.exr").items()
        if name in ("diffuse", "specular", "albedo", "normal")
    }
    expected = tf.diffuse_forward(oidn_bases(layers, base)["diffuse"], layers["albedo"])[y : y + 32, x : x + 32]
    # stored as float16: 2^-11 relative rounding of log values
    np.testing.assert_allclose(item["base"], expected.transpose(2, 0, 1), rtol=2**-10, atol=1e-6)


def test_a_store_without_bases_is_refused_naming_the_scene_and_the_key(tmp_path, variant):
    cfg = load_config(None, tiny_store_overrides(tmp_path, 64, 32) + ["tile.oidn_base=false"])
    store = build_dataset(cfg, progress=False).store
    assert len(PatchReader(store, "train")) > 0  # valid for the noisy base
    with pytest.raises(PatchStoreError, match=r"scene train/\S+ has no OIDN bases.*tile.oidn_base = true"):
        PatchReader(store, "train", base="oidn")


def test_bases_of_another_quality_are_refused_per_branch_naming_the_scene_and_the_key(store_with_bases):
    """The two refining bases share their diffuse bases (OIDN high) and differ on the specular branch."""
    cfg, store = store_with_bases
    other = next(base for base in BASE_QUALITIES if base != cfg.tile.refiner_base)
    assert len(PatchReader(store, "train", branch="diffuse", base=other)) > 0
    stored, needed = BASE_QUALITIES[cfg.tile.refiner_base]["specular"], BASE_QUALITIES[other]["specular"]
    with pytest.raises(
        PatchStoreError,
        match=rf"scene train/\S+ holds specular OIDN bases of quality '{stored}', "
        rf"model.base '{other}' trains on '{needed}' ones; tile with "
        rf"tile.refiner_base = '{other}'",
    ):
        PatchReader(store, "train", branch="specular", base=other)


def test_scenes_tiled_before_the_fast_bases_read_as_high_on_both_branches():
    from admc.stores.patches.reader import stored_quality

    old = {"method": "oidn", "quality": "high", "per_branch": True}  # what tiling recorded until then
    assert [stored_quality(old, branch) for branch in ("diffuse", "specular")] == ["high", "high"]
    assert stored_quality({"quality": BASE_QUALITIES["oidn-fast"]}, "specular") == "fast"


def test_a_refiner_trains_selects_and_denoises_as_oidn_plus_a_correction(store_with_bases, tmp_path):
    cfg, store = store_with_bases
    model, settings = preset("default")
    base = cfg.tile.refiner_base
    model = dataclasses.replace(model, **TINY, critic_channels=4, base=base)
    settings = dataclasses.replace(
        settings,
        steps=4,
        l1_warmup_steps=2,
        critic_only_steps=1,
        val_every=2,
        val_patches=2,
        checkpoint_every=2,
        log_every=1,
        head_tail_start_step=0,
    )
    result = train(store, tmp_path / "run", settings, model, progress=False)
    assert result.validation["diffuse"]["base_relmse"] > 0  # OIDN's own score: what the run must beat
    from admc.model.inference.denoiser import load_denoiser
    from admc.model.inference.options import DenoiserOptions

    denoiser = load_denoiser(result.weights)
    assert denoiser.name == "admc+oidn" and denoiser.base == base
    layers = exr.read_exr(cfg.workdir_path("renders") / store_scene(store) / "spp0004.exr")
    out = denoiser(layers)
    assert out.image.shape == layers["diffuse"].shape and np.isfinite(out.image).all()
    assert out.base_seconds > 0
    dark = load_denoiser(result.weights, DenoiserOptions(dark_pass=True))(
        layers
    )  # OIDN runs again at the second exposure
    assert np.isfinite(dark.image).all() and (dark.dark_share == 0) == np.array_equal(dark.image, out.image)


def store_scene(store):
    return patches.list_scenes(store, "train")[0]


@pytest.mark.parametrize("base", sorted(BASE_QUALITIES))
def test_an_untrained_refiner_denoises_exactly_like_per_branch_oidn_at_its_quality(
    store_with_bases, inference_dtype, base
):
    cfg, store = store_with_bases
    specular_scene = PatchReader(store, "train", branch="specular").scenes[0]
    layers = exr.read_exr(cfg.workdir_path("renders") / specular_scene / "spp0004.exr")
    layers["coverage"] = np.ones_like(layers["coverage"])  # every pixel goes through the network
    branches = {b: refiner(base=base) for b in ("diffuse", "specular")}
    out = FullImageDenoiser(branches["diffuse"], branches["specular"], DenoiserOptions(tile=24, dtype=inference_dtype))(
        layers
    )
    clean = {name: sanitize(layers[name], name)[0] for name in ("diffuse", "specular", "albedo", "normal")}
    bases = oidn_bases(clean, base)
    # the untrained correction is exactly zero in either precision (its last conv starts at zero) and
    # adding it to the float32 base stays float32: the log transform and its inverse round trip in float32
    np.testing.assert_allclose(out.diffuse, bases["diffuse"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.specular, bases["specular"], rtol=1e-5, atol=1e-6)


def test_fine_tuning_refuses_weights_of_the_other_base():
    from admc.errors import TrainingError
    from admc.model.training.resume import load_init
    from admc.pipeline.weights import shipped_weights

    model = load_config(None, []).model
    noisy_weights = shipped_weights(model)
    with pytest.raises(TrainingError, match=r"model.base = 'noisy', this config has model.base = 'oidn'"):
        load_init(noisy_weights, dataclasses.replace(model, base="oidn"))


def test_a_refiner_fine_tunes_from_a_refiner_of_bases_of_another_quality():
    """The network is the same: the shipped refiner is where a refiner of the other OIDN quality starts."""
    from admc.model.training.resume import load_init
    from admc.pipeline.weights import shipped_weights

    model = load_config(None, []).model
    for base in BASE_QUALITIES:
        start = shipped_weights(dataclasses.replace(model, base=base))
        assert start is not None and ModelSettings.from_saved(read_networks(start)[1]).base in BASE_QUALITIES
        other = next(b for b in BASE_QUALITIES if b != ModelSettings.from_saved(read_networks(start)[1]).base)
        nets, _, description = load_init(start, dataclasses.replace(model, base=other))
        assert set(nets) == {"diffuse", "specular"} and "a refiner of model.base" in description
