"""The multi-scale (U-Net) CFM generator: shapes, reach, exact tiling, settings and a real training step."""

import dataclasses

import numpy as np
import pytest
import torch
from torch import nn

from admc.model.inference.denoiser import FullImageDenoiser, load_denoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.tiling import receptive_radius, run_tiled
from admc.model.nets.backbones import build_generator
from admc.model.nets.generator import Generator, scaled_kaiming_
from admc.model.nets.settings import ModelSettings
from admc.model.nets.unet import UNetGenerator
from admc.model.training.branch import BranchTrainer
from admc.model.train_settings import TrainSettings
from admc.model.transforms import EPS, diffuse_forward, transform_spec
from admc.stores.checkpoints import export_weights
from test_inference import log_tolerance

TINY = ModelSettings(channels=4, blocks=1, cond_channels=4, encoder_channels=8, backbone="unet", levels=2)


def strong_unet(seed: int, config: ModelSettings = TINY) -> UNetGenerator:
    """Weights at 0.7x Kaiming and positive biases: far pixels change the output clearly, values stay O(1)."""
    torch.manual_seed(seed)
    g = build_generator(config).eval()
    scaled_kaiming_(g, 0.7)
    with torch.no_grad():
        for m in g.modules():
            if isinstance(m, nn.Conv2d):
                m.bias.uniform_(0.0, 0.1)
    return g


def test_the_backbone_setting_builds_the_unet_and_keeps_the_paper_body_by_default():
    assert isinstance(build_generator(TINY), UNetGenerator)
    assert type(build_generator(dataclasses.replace(TINY, backbone="residual"))) is Generator
    assert ModelSettings().backbone == "residual"
    with pytest.raises(ValueError, match="backbone"):
        ModelSettings(backbone="vit").check()


@pytest.mark.parametrize("size", [(1, 1), (5, 3), (37, 23), (64, 64)])
def test_any_size_comes_back_the_same_size_and_non_negative(size):
    g = strong_unet(0)
    x, f = torch.rand(2, 3, *size), torch.rand(2, 7, *size)
    with torch.no_grad():
        out = g(x, f)
    assert out.shape == x.shape and bool((out >= 0).all()) and bool(torch.isfinite(out).all())


def test_a_flat_image_of_any_size_stays_flat_up_to_its_border():
    """Sizes off the coarse grid are padded by repeating the edge; zero padding made the bottom and right
    border differ from the interior (a frame, as the paper body had before its convs repeated the edge)."""
    g = strong_unet(2)
    for height, width in [(37, 23), (16, 16), (9, 30)]:
        x, f = torch.full((1, 3, height, width), 0.4), torch.full((1, 7, height, width), 0.3)
        with torch.no_grad():
            out = g(x, f)[0].numpy()
        # Every pixel sums the same float32 products; oneDNN may order them differently at row ends.
        np.testing.assert_allclose(out, np.broadcast_to(out[:, :1, :1], out.shape), rtol=1e-5, atol=0)


@pytest.mark.parametrize("levels,blocks", [(1, 1), (2, 1), (3, 2)])
def test_receptive_radius_bounds_an_impulse_and_is_not_loose(levels, blocks):
    g = strong_unet(1, dataclasses.replace(TINY, levels=levels, blocks=blocks))
    radius = receptive_radius(g)
    size = 2 * radius + 2**levels * 3 + 1
    reach = 0
    for offset in range(2**levels):  # the reach depends on where the impulse sits on the coarse grid
        x, f = torch.rand(1, 3, size, size), torch.rand(1, 7, size, size)
        centre = size // 2 + offset
        with torch.no_grad():
            before = g(x, f)
            x[0, :, centre, centre] += 1.0
            changed = (g(x, f) - before).abs().amax(dim=1)[0] > 0
        ys, xs = torch.nonzero(changed, as_tuple=True)
        reach = max(reach, int((ys - centre).abs().max()), int((xs - centre).abs().max()))
    assert radius - 2**levels <= reach <= radius


def test_tiles_on_the_coarse_grid_equal_the_untiled_image_and_unaligned_tiles_do_not():
    g = strong_unet(2)
    radius = receptive_radius(g)
    x, f = torch.rand(1, 3, 70, 91) * 3, torch.rand(1, 7, 70, 91)
    with torch.no_grad():
        untiled = g(x, f)
        tiled = run_tiled(g, x, f, tile=16, halo=radius, align=g.alignment)
        unaligned = run_tiled(g, x, f, tile=16, halo=radius, align=1)
    scale = untiled.abs().max().item()
    assert scale > 0.5
    # float32 sums in another order (oneDNN's kernel depends on the crop's shape): ~1e-6 relative
    assert (tiled - untiled).abs().max().item() <= 1e-5 * scale
    assert (unaligned - untiled).abs().max().item() > 1e-3 * scale  # the check can fail


def test_full_image_denoiser_tiles_a_unet_exactly_and_loads_it_from_weights(tmp_path, inference_dtype):
    rng = np.random.default_rng(0)
    layers = {
        "diffuse": rng.gamma(0.5, 2.0, (45, 60, 3)).astype(np.float32),
        "albedo": rng.random((45, 60, 3), dtype=np.float32),
        "normal": np.tile(np.array([0, 0, 1], np.float32), (45, 60, 1)),
    }
    g = strong_unet(3)
    tiled = FullImageDenoiser(g, None, DenoiserOptions(tile=16, dtype=inference_dtype))(layers)
    untiled = FullImageDenoiser(g, None, DenoiserOptions(tile=512, dtype=inference_dtype))(layers)
    assert tiled.tiles == 12 and untiled.tiles == 1
    tolerance = log_tolerance(inference_dtype, np.abs(diffuse_forward(untiled.diffuse, layers["albedo"])).max())
    gain = np.abs(untiled.diffuse) + layers["albedo"] + EPS  # d(linear)/d(log), as in test_inference
    rounding = 4 * np.finfo(np.float32).eps * np.abs(untiled.diffuse)  # the inverse transform in float32
    assert np.all(np.abs(tiled.diffuse - untiled.diffuse) <= gain * tolerance * 1.001 + rounding)

    model = ModelSettings(
        channels=4, blocks=1, cond_channels=4, encoder_channels=8, critic_channels=4, backbone="unet", levels=2
    )
    path = tmp_path / "unet.pt"
    export_weights(
        path,
        {"diffuse": {"generator": g.state_dict(), "critic": {}}},
        {"model": dataclasses.asdict(model), "transform": transform_spec(), "patch_size": 32},
    )
    loaded = load_denoiser(path, DenoiserOptions(tile=16))
    assert isinstance(loaded.generators["diffuse"], UNetGenerator)
    for name, value in loaded.generators["diffuse"].state_dict().items():  # the fp16 file's values
        assert torch.equal(value, g.state_dict()[name].half().float()), name


def test_weights_saved_before_the_backbone_setting_load_as_the_paper_body():
    saved = {k: v for k, v in dataclasses.asdict(ModelSettings(channels=8)).items() if k not in ("backbone", "levels")}
    assert ModelSettings.from_saved(saved) == ModelSettings(channels=8)


def test_a_unet_branch_takes_real_adversarial_training_steps():
    torch.manual_seed(0)
    model = ModelSettings(
        channels=4, blocks=1, cond_channels=4, encoder_channels=8, critic_channels=4, backbone="unet", levels=2
    )
    settings = TrainSettings(
        steps=3,
        batch_size=2,
        l1_warmup_steps=0,
        critic_only_steps=0,
        head_tail_start_step=0,
        lr_milestones=(10,),
        device="cpu",
    )
    trainer = BranchTrainer("diffuse", model, settings, 32, torch.device("cpu"))
    batch = {
        "noisy": torch.rand(2, 3, 32, 32),
        "features": torch.rand(2, 7, 32, 32),
        "reference": torch.rand(2, 3, 32, 32),
    }
    before = {k: v.clone() for k, v in trainer.generator.state_dict().items()}
    ok, losses = trainer.step(0, [batch])
    assert ok and np.isfinite(losses["generator_loss"]) and np.isfinite(losses["critic_loss"])
    assert any(not torch.equal(before[k], v) for k, v in trainer.generator.state_dict().items())
