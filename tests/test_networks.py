"""The denoiser (EncoderNet + CFM generator, every ablation mode) and the VGG-128 critic, on CPU."""

import pytest
import torch

from admc.model.nets.critic import Critic
from admc.model.nets.encoder import EncoderNet
from admc.model.nets.generator import CFMLayer, Generator
from admc.model.nets.losses import generator_loss
from admc.model.nets.settings import MODES, ModelSettings

TINY = dict(channels=8, blocks=2, cond_channels=8, encoder_channels=16)


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def test_cfm_is_the_identity_when_gamma_is_one_and_beta_zero():
    torch.manual_seed(0)
    cfm = CFMLayer(channels=8, cond_channels=4)
    x, cond = torch.randn(2, 8, 5, 7), torch.randn(2, 4, 5, 7)
    assert not torch.equal(cfm(x, cond), x)
    with torch.no_grad():
        for net in (cfm.scale, cfm.shift):
            net[-1].weight.zero_()
            net[-1].bias.zero_()
    assert torch.equal(cfm(x, cond), x)


def test_cfm_output_is_x_times_one_plus_scale_plus_shift():
    torch.manual_seed(0)
    cfm = CFMLayer(channels=8, cond_channels=4)
    x, cond = torch.randn(2, 8, 5, 7), torch.randn(2, 4, 5, 7)
    expected = x * (cfm.scale(cond) + 1) + cfm.shift(cond)
    torch.testing.assert_close(cfm(x, cond), expected)


def test_encoder_keeps_resolution_and_gives_the_condition_channels():
    out = EncoderNet(hidden_channels=16, out_channels=8)(torch.rand(2, 7, 9, 13))
    assert out.shape == (2, 8, 9, 13)


@pytest.mark.parametrize("mode", MODES)
def test_every_mode_trains_one_step(mode):
    torch.manual_seed(0)
    g = Generator(ModelSettings(**TINY, mode=mode))
    noisy, features, clean = torch.rand(2, 3, 32, 32), torch.rand(2, 7, 32, 32), torch.rand(2, 3, 32, 32)
    before = [p.detach().clone() for p in g.parameters()]
    out = g(noisy, features)
    assert out.shape == noisy.shape and torch.isfinite(out).all() and (out >= 0).all()
    loss, _ = generator_loss(out, clean, None, adversarial=False)
    loss.backward()
    torch.optim.Adam(g.parameters(), lr=1e-3).step()
    changed = [not torch.equal(a, b) for a, b in zip(before, g.parameters())]
    assert sum(changed) == len(changed), f"{len(changed) - sum(changed)} parameter tensors did not move"


@pytest.mark.parametrize("mode", MODES)
def test_modes_have_the_cfm_parts_they_claim(mode):
    g = Generator(ModelSettings(**TINY, mode=mode))
    cfms = [m for m in g.modules() if isinstance(m, CFMLayer)]
    if mode in ("none", "concat"):
        assert cfms == [] and g.encoder is None
    else:
        assert len(cfms) == 2 * TINY["blocks"] + 1 and g.encoder is not None
        assert all((c.scale is not None) == (mode in ("cfm", "scale")) for c in cfms)
        assert all((c.shift is not None) == (mode in ("cfm", "shift")) for c in cfms)
    assert g.head.in_channels == (10 if mode == "concat" else 3)


@pytest.mark.parametrize("mode", ["cfm", "concat", "none"])
def test_output_shape_matches_odd_input_sizes(mode):
    g = Generator(ModelSettings(**TINY, mode=mode)).eval()
    with torch.no_grad():
        assert g(torch.rand(1, 3, 33, 47), torch.rand(1, 7, 33, 47)).shape == (1, 3, 33, 47)


def test_channels_last_gives_the_same_output():
    torch.manual_seed(0)
    g = Generator(ModelSettings(**TINY)).eval()
    noisy, features = torch.rand(2, 3, 17, 23), torch.rand(2, 7, 17, 23)
    with torch.no_grad():
        expected = g(noisy, features)
        g_cl = g.to(memory_format=torch.channels_last)
        out = g_cl(noisy.to(memory_format=torch.channels_last), features.to(memory_format=torch.channels_last))
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-6)


def test_none_mode_needs_no_features_and_others_reject_bad_ones():
    assert Generator(ModelSettings(**TINY, mode="none"))(torch.rand(1, 3, 8, 8)).shape == (1, 3, 8, 8)
    g = Generator(ModelSettings(**TINY))
    with pytest.raises(ValueError, match="features are required"):
        g(torch.rand(1, 3, 8, 8))
    with pytest.raises(ValueError, match="features must be"):
        g(torch.rand(1, 3, 8, 8), torch.rand(1, 6, 8, 8))
    with pytest.raises(ValueError, match="noisy must be"):
        g(torch.rand(1, 4, 8, 8), torch.rand(1, 7, 8, 8))
    with pytest.raises(ValueError, match="mode"):
        Generator(ModelSettings(mode="film"))


def test_paper_generator_has_the_authors_parameter_count():
    g = Generator(ModelSettings())
    assert count(g) == 1_530_019  # 1.53 M in the implementation notes
    assert count(g.encoder) == 61_856  # ~62 k
    assert count(g.body_cfm) == 6_336  # ~6.3 k per CFM layer


def test_generator_init_is_kaiming_fan_in_scaled_by_a_tenth():
    torch.manual_seed(0)
    conv = Generator(ModelSettings()).blocks[0].conv1  # 64 -> 64, 3x3: fan-in 576
    expected_std = 0.1 * (2.0 / 576) ** 0.5
    assert conv.weight.std().item() == pytest.approx(expected_std, rel=0.02)
    assert torch.count_nonzero(conv.bias) == 0


def test_parameter_groups_split_head_and_tail_from_the_body():
    g = Generator(ModelSettings(**TINY))
    groups = g.parameter_groups()
    head_tail = sum(p.numel() for p in groups["head_tail"])
    assert head_tail == count(g.head) + count(g.tail)
    assert head_tail + sum(p.numel() for p in groups["body"]) == count(g)


@pytest.mark.parametrize("norm,expected", [("none", 14_496_521), ("layer", 14_502_281), ("batch", 14_502_281)])
def test_paper_critic_parameter_count(norm, expected):
    n = count(Critic(ModelSettings(critic_norm=norm)))
    assert n == expected and abs(n - 14.5e6) / 14.5e6 < 0.1


def test_paper_critic_scores_128_patches():
    c = Critic()
    assert c.classifier[0].in_features == 8192
    with torch.no_grad():
        assert c(torch.rand(2, 3, 128, 128)).shape == (2, 1)


@pytest.mark.parametrize("norm", ["none", "layer", "batch"])
def test_tiny_critic_on_32_patches(norm):
    c = Critic(ModelSettings(critic_channels=8, critic_norm=norm), patch_size=32)
    assert c.classifier[0].in_features == 64  # 8 * 8 channels at 1x1
    out = c(torch.rand(3, 3, 32, 32))
    assert out.shape == (3, 1) and torch.isfinite(out).all()


def test_critic_rejects_wrong_patch_sizes():
    with pytest.raises(ValueError, match="patch_size"):
        Critic(patch_size=48)
    with pytest.raises(ValueError, match="critic_norm"):
        Critic(ModelSettings(critic_norm="instance"))
    with pytest.raises(ValueError, match=r"\(N, 3, 32, 32\)"):
        Critic(ModelSettings(critic_channels=8), patch_size=32)(torch.rand(1, 3, 64, 64))


def test_input_skip_starts_at_the_identity():
    """With the tail's last conv zeroed, an input-skip generator returns its (non-negative) input."""
    torch.manual_seed(0)
    net = Generator(ModelSettings(channels=8, blocks=1, cond_channels=8, encoder_channels=8, input_skip=True))
    torch.nn.init.zeros_(net.tail[2].weight)
    torch.nn.init.zeros_(net.tail[2].bias)
    noisy, features = torch.rand(2, 3, 9, 11), torch.rand(2, 7, 9, 11)
    torch.testing.assert_close(net(noisy, features), noisy)
    plain = Generator(ModelSettings(channels=8, blocks=1, cond_channels=8, encoder_channels=8))
    torch.nn.init.zeros_(plain.tail[2].weight)
    torch.nn.init.zeros_(plain.tail[2].bias)
    with torch.no_grad():
        assert float(plain(noisy, features).abs().max()) == 0.0  # the authors' network starts at zero


# Widening weights into model.noise_input. In float64 the widened generator must compute what the saved one
# did: its first conv adds one product w * noise with w = 0 exactly, so the only possible difference is the
# order oneDNN sums the other products in (it may block 8 input channels differently from 7). Each output
# is then a sum over at most ~10 layers of <= 9 * 64 products of magnitude <= ~10: a reordering moves it by
# at most that count times eps64 (2.2e-16) times the sum, < 1e-11. (float32 saw a 2.4e-7 reordering.)
WIDEN_ATOL = 1e-11


@pytest.mark.parametrize(
    "mode, backbone, base",
    [
        ("cfm", "residual", "noisy"),
        ("concat", "residual", "noisy"),
        ("cfm", "unet", "noisy"),
        ("shift", "residual", "oidn"),
    ],
)
def test_weights_without_the_noise_input_widen_to_the_same_function(mode, backbone, base):
    """Fine-tuning older weights into model.noise_input: zero weights on the new channel, and the
    widened generator computes what the saved one did, whatever the noise map holds."""
    import dataclasses

    from admc.model.nets.backbones import build_generator
    from admc.model.training.resume import with_noise_input

    model = ModelSettings(**TINY, mode=mode, backbone=backbone, levels=2, base=base, input_skip=True)
    torch.manual_seed(0)
    old = build_generator(model)
    for p in old.parameters():  # every weight nonzero, the refiner's zero-started tail too
        torch.nn.init.normal_(p, std=0.1)
    wide_model = dataclasses.replace(model, noise_input=True)
    wide = build_generator(wide_model)
    wide.load_state_dict(with_noise_input(old.state_dict(), wide_model))
    old, wide = old.double(), wide.double()
    noisy, feats = torch.rand(2, 3, 16, 16, dtype=torch.float64), torch.rand(2, 7, 16, 16, dtype=torch.float64)
    base_image = torch.rand(2, 3, 16, 16, dtype=torch.float64) if base == "oidn" else None
    with torch.no_grad():
        want = old(noisy, feats, base_image)
        got = wide(noisy, torch.cat([feats, torch.rand(2, 1, 16, 16, dtype=torch.float64)], dim=1), base_image)
    torch.testing.assert_close(got, want, rtol=0, atol=WIDEN_ATOL)
    with pytest.raises(ValueError, match=r"features must be \(2, 8, 16, 16\)"):
        wide(noisy, feats, base_image)


@pytest.mark.parametrize(
    "name", ["admc-small-pretrained.pt", "admc-small-refiner.pt", "admc-small-refiner-fast.pt", "admc-small-unet.pt"]
)
def test_finetuning_the_shipped_weights_into_the_noise_input_starts_exactly_at_them(name):
    """What `admc-pipe train --stage finetune --set model.noise_input=true` starts from (resume.load_init):
    the shipped tensors bit for bit, zeros on the noise channel, and the same outputs at step 0."""
    import dataclasses

    from admc.model.nets.backbones import build_generator
    from admc.model.training.resume import load_init
    from admc.pipeline.weights import WEIGHTS_DIR, shipped_weights
    from admc.stores.checkpoints import read_networks

    path = WEIGHTS_DIR / name
    shipped, saved, _ = read_networks(path)
    plain = ModelSettings.from_saved(saved)
    model = dataclasses.replace(plain, noise_input=True)
    assert shipped_weights(model) == shipped_weights(plain)  # a noise model without its own: these
    nets, _, source = load_init(path, model)
    assert source == f"{path} (the noise input added, its weights starting at 0)"
    torch.manual_seed(1)
    for branch, state in shipped.items():
        old, new = state["generator"], nets[branch]["generator"]
        assert set(old) == set(new)
        for key, tensor in old.items():
            if key == "encoder.layers.0.weight":  # features (7), [noise], [a refiner's noisy (3)]
                assert torch.equal(new[key][:, :7], tensor[:, :7]) and torch.equal(new[key][:, 8:], tensor[:, 7:])
                assert torch.equal(new[key][:, 7], torch.zeros_like(tensor[:, 0]))
            else:
                assert torch.equal(new[key], tensor), key
        before, after = build_generator(plain), build_generator(model)
        before.load_state_dict({k: v.double() for k, v in old.items()})
        after.load_state_dict({k: v.double() for k, v in new.items()})
        before, after = before.double().eval(), after.double().eval()
        noisy, feats = torch.rand(1, 3, 40, 40, dtype=torch.float64), torch.rand(1, 7, 40, 40, dtype=torch.float64)
        base = noisy.flip(-1) if plain.base != "noisy" else None
        with torch.no_grad():
            want = before(noisy, feats, base)
            got = after(noisy, torch.cat([feats, torch.rand(1, 1, 40, 40, dtype=torch.float64)], dim=1), base)
        torch.testing.assert_close(got, want, rtol=0, atol=WIDEN_ATOL)


@pytest.mark.parametrize("cfm_per_block, condition_layers", [(1, 2), (2, 1), (1, 1)])
def test_slimmer_generators_have_the_layers_they_claim_and_train(cfm_per_block, condition_layers):
    """model.cfm_per_block / model.condition_layers: fewer full-resolution 1x1 convs, the same receptive field."""
    torch.manual_seed(0)
    full = Generator(ModelSettings(**TINY))
    g = Generator(ModelSettings(**TINY, cfm_per_block=cfm_per_block, condition_layers=condition_layers))
    cfms = [m for m in g.modules() if isinstance(m, CFMLayer)]
    assert len(cfms) == TINY["blocks"] * cfm_per_block + 1  # the blocks' and the body's last
    for cfm in cfms:
        for net in (cfm.scale, cfm.shift):
            assert sum(isinstance(m, torch.nn.Conv2d) for m in net.modules()) == condition_layers
    assert g.receptive_radius() == full.receptive_radius()
    noisy, features, clean = torch.rand(2, 3, 17, 19), torch.rand(2, 7, 17, 19), torch.rand(2, 3, 17, 19)
    loss, _ = generator_loss(g(noisy, features), clean, None, adversarial=False)
    loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in g.parameters())


@pytest.mark.parametrize("key, value", [("cfm_per_block", 3), ("condition_layers", 0)])
def test_slimness_settings_outside_one_or_two_are_refused_naming_the_key(key, value):
    with pytest.raises(ValueError, match=rf"^{key}: must be 1 or 2, got {value}"):
        ModelSettings(**{key: value}).check()
    with pytest.raises(ValueError, match=rf"^{key}: must be 1 or 2"):
        Generator(ModelSettings(**{key: value}))


# Slimming by least squares (model/training/slimming.py) in float64. Where the slim network can compute the
# full one exactly, the fit recovers it up to the solver's rounding: the normal equations of at most
# 145 unknowns over 2 x 24 x 24 pixels, condition number well under 1e6 for random inputs, times eps64
# (2.2e-16), then a few layers of sums of <= 144 products of magnitude ~1: far below 1e-8.
SLIM_ATOL = 1e-8


def _affine_condition_nets(g: Generator) -> None:
    """Make every two-layer condition net affine on inputs in [0, 1): a first layer with positive weights
    and bias, so the LeakyReLU between the two layers passes everything through."""
    with torch.no_grad():
        for cfm in (m for m in g.modules() if isinstance(m, CFMLayer)):
            for net in (cfm.scale, cfm.shift):
                net[0].weight.uniform_(0.0, 0.5)
                net[0].bias.uniform_(0.1, 0.5)


def _slim_pair(cfm_per_block: int, condition_layers: int, encoder_nonnegative: bool):
    from admc.model.training.slimming import slim_generator

    torch.manual_seed(0)
    full = Generator(ModelSettings(**TINY)).double()
    for p in full.parameters():
        torch.nn.init.normal_(p, std=0.2)
    _affine_condition_nets(full)
    if encoder_nonnegative:  # condition maps >= 0: the affine condition nets see only inputs they pass through
        full.encoder.layers.append(torch.nn.ReLU())
    slim = Generator(ModelSettings(**TINY, cfm_per_block=cfm_per_block, condition_layers=condition_layers)).double()
    if encoder_nonnegative:
        slim.encoder.layers.append(torch.nn.ReLU())
    batch = {
        "noisy": torch.rand(2, 3, 24, 24, dtype=torch.float64),
        "features": torch.rand(2, 7, 24, 24, dtype=torch.float64),
    }
    slim_generator(full, slim, batch, seed=0)
    return full, slim, batch


def test_slimming_recovers_a_network_the_slim_one_can_compute_exactly():
    """One-layer condition nets fitted to two-layer nets that are affine on the condition maps they see
    compute the same function."""
    full, slim, batch = _slim_pair(cfm_per_block=2, condition_layers=1, encoder_nonnegative=True)
    with torch.no_grad():
        torch.testing.assert_close(
            slim(batch["noisy"], batch["features"]), full(batch["noisy"], batch["features"]), rtol=0, atol=SLIM_ATOL
        )


def test_slimming_a_block_refits_its_second_conv_to_the_full_blocks_output():
    """Dropping each block's second CFM: the refitted second conv makes the slim network closer to the full
    one than copying the conv would, and equal to it where that CFM was the identity."""
    from admc.model.training.slimming import slim_generator

    full, slim, batch = _slim_pair(cfm_per_block=1, condition_layers=2, encoder_nonnegative=False)
    copied = Generator(slim.config).double()
    copied.load_state_dict(full.state_dict(), strict=False)
    inputs = (batch["noisy"], batch["features"])
    with torch.no_grad():
        want = full(*inputs)
        assert (slim(*inputs) - want).abs().mean() < 0.5 * (copied(*inputs) - want).abs().mean()
        for block in full.blocks:  # the second CFM now multiplies by 1 and adds 0
            for net in (block.cfm[1].scale, block.cfm[1].shift):
                net[-1].weight.zero_()
                net[-1].bias.zero_()
    refitted = Generator(slim.config).double()
    slim_generator(full, refitted, batch, seed=0)
    with torch.no_grad():
        torch.testing.assert_close(refitted(*inputs), full(*inputs), rtol=0, atol=SLIM_ATOL)
