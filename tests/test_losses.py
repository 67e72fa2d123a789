"""Generator L1 (+ display SSIM) + adversarial loss, WGAN-GP critic loss and the float32 gradient penalty."""

import numpy as np
import pytest
import torch
from torch import nn

from admc.common import metrics
from admc.model.nets.critic import Critic
from admc.model.nets.generator import Generator
from admc.model.nets.settings import ModelSettings
from admc.model.nets.losses import (
    critic_loss,
    display,
    display_ssim_loss,
    generator_loss,
    gradient_penalty,
    log_floor,
    ms_ssim,
    oidn_loss,
)
from admc.model.train_settings import TrainSettings


class LinearCritic(nn.Module):
    """D(x) = <w, x> + b: its input gradient is w everywhere, so the GP is (||w|| - 1)^2 exactly.
    Built on nn.Linear so autocast really runs it in bf16 when the GP fails to turn autocast off."""

    def __init__(self, w: torch.Tensor) -> None:
        super().__init__()
        self.linear = nn.Linear(w.numel(), 1)
        with torch.no_grad():
            self.linear.weight.copy_(w.reshape(1, -1))

    def forward(self, x):
        return self.linear(x.flatten(1))


def random_direction(shape, norm, seed=0):
    w = torch.randn(shape, generator=torch.Generator().manual_seed(seed))
    return w * (norm / w.norm())


@pytest.mark.parametrize("w_norm", [0.3, 1.0, 2.5])
def test_gradient_penalty_of_a_linear_critic_is_norm_minus_one_squared(w_norm):
    critic = LinearCritic(random_direction((3, 8, 8), w_norm))
    real, fake = torch.rand(4, 3, 8, 8), torch.rand(4, 3, 8, 8)
    gp = gradient_penalty(critic, real, fake)
    assert gp.item() == pytest.approx((w_norm - 1) ** 2, abs=1e-6)


def test_gradient_penalty_is_float32_and_unchanged_under_bf16_autocast():
    critic = LinearCritic(random_direction((3, 8, 8), 2.5))
    real, fake = torch.rand(4, 3, 8, 8), torch.rand(4, 3, 8, 8)
    reference = gradient_penalty(critic, real, fake)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        gp = gradient_penalty(critic, real.bfloat16(), fake.bfloat16())
        assert critic(real).dtype == torch.bfloat16  # autocast is really on around the call
    assert gp.dtype == torch.float32
    assert gp.item() == pytest.approx(reference.item(), rel=1e-6)


def test_gradient_penalty_of_a_real_critic_matches_float32_under_autocast():
    torch.manual_seed(0)
    critic = Critic(ModelSettings(critic_channels=4), patch_size=32)
    real, fake = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    torch.manual_seed(1)
    reference = gradient_penalty(critic, real, fake)
    torch.manual_seed(1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        gp = gradient_penalty(critic, real, fake)
    assert gp.dtype == torch.float32
    torch.testing.assert_close(gp, reference, rtol=1e-5, atol=1e-7)


def test_gradient_penalty_trains_the_critic():
    critic = LinearCritic(random_direction((3, 4, 4), 2.0))
    gp = gradient_penalty(critic, torch.rand(2, 3, 4, 4), torch.rand(2, 3, 4, 4))
    gp.backward()
    # d/dw (||w|| - 1)^2 = 2 (||w|| - 1) w / ||w|| = w here (||w|| = 2)
    torch.testing.assert_close(critic.linear.weight.grad, critic.linear.weight.detach(), rtol=1e-5, atol=1e-6)


def test_generator_loss_weights_l1_and_adversarial_terms():
    fake, real = torch.full((2, 3, 4, 4), 0.5), torch.full((2, 3, 4, 4), 0.25)
    critic_fake = torch.tensor([[2.0], [4.0]])
    total, parts = generator_loss(fake, real, critic_fake)
    assert parts["l1"].item() == pytest.approx(0.25)
    assert parts["adversarial"].item() == pytest.approx(-3.0)
    assert total.item() == pytest.approx(0.25 - 5e-3 * 3.0)
    l1_only, parts = generator_loss(fake, real, None, l1_weight=2.0, adversarial=False)
    assert l1_only.item() == pytest.approx(0.5) and set(parts) == {"l1"}
    with pytest.raises(ValueError, match="critic_fake is required"):
        generator_loss(fake, real, None)


def test_log_floor_is_log_of_linear_plus_floor_and_stays_finite():
    y = torch.linspace(0, 12, 241, dtype=torch.float64)
    assert torch.equal(log_floor(y.float(), 1.0), y.float())  # the networks' own domain, unchanged
    for floor in (0.01, 0.1, 0.5, 4.0):
        want = torch.log(torch.expm1(y) + floor)
        assert torch.allclose(log_floor(y.float(), floor).double(), want, rtol=1e-6, atol=1e-6)  # float32 rounding
        h = 1e-3 * floor  # slope 1 / floor at 0: each side moves by 1e-3 (its curvature adds < 0.2% here)
        x = torch.tensor([-3.0, -h, 0.0, h, 50.0, 1e4], requires_grad=True)
        out = log_floor(x, floor)
        out.sum().backward()
        assert torch.isfinite(out).all() and torch.isfinite(x.grad).all()
        assert x.grad.max().item() <= max(1.0, 1 / floor) * (1 + 1e-5)
        # continuous, with a continuous slope (1 / floor), across 0 where the tangent takes over
        assert (out[2] - out[1]).item() == pytest.approx(1e-3, rel=5e-3)  # float32 ulp at |log 0.01|: 5e-4
        assert (out[3] - out[2]).item() == pytest.approx(1e-3, rel=5e-3)


def test_a_smaller_l1_floor_weighs_an_error_in_a_dark_pixel_more():
    """Same error in the log1p domain, once on a dark pixel (linear 0.01) and once on a bright one (10)."""
    dark, bright = torch.log1p(torch.tensor(0.01)), torch.log1p(torch.tensor(10.0))
    real = torch.stack([dark, bright]).reshape(1, 1, 1, 2)
    error = torch.tensor([0.05, 0.0]).reshape(1, 1, 1, 2), torch.tensor([0.0, 0.05]).reshape(1, 1, 1, 2)
    for floor, dark_over_bright in ((1.0, (0.99, 1.01)), (0.1, (5, 15))):  # 0.1: 7.1 in exact arithmetic
        (on_dark, _), (on_bright, _) = (
            generator_loss(real + e, real, None, adversarial=False, l1_floor=floor) for e in error
        )
        lo, hi = dark_over_bright
        assert lo <= on_dark.item() / on_bright.item() <= hi


def _textured(level: float, shape=(1, 3, 32, 32), seed=0) -> torch.Tensor:
    """log1p of linear radiance around `level` with +-20% texture: a patch that SSIM has structure to compare."""
    texture = torch.rand(shape, generator=torch.Generator().manual_seed(seed))
    return torch.log1p(level * (0.8 + 0.4 * texture))


def test_display_matches_the_metrics_tone_map_to_within_its_offset():
    linear = torch.tensor([0.0, 5.1e-6, 1e-3, 0.2, 1.0, 7.0], dtype=torch.float64)
    rounded = metrics.to_ldr(linear.numpy().reshape(1, -1, 1)).ravel().astype(np.float64)
    # the offset moves a value by at most (offset^(1/2.2)) * 255 = 1.6 levels, and only near 0
    assert np.abs(display(linear).numpy() - rounded).max() <= 0.5 + 1.7
    assert display(linear)[0] == 0 and display(linear)[-1] == display(linear)[-2]


def test_the_display_ssim_term_weighs_a_darkened_shadow_like_a_darkened_grey_the_l1_does_not():
    """The same 20% darkening, once of a deep shadow (linear 3e-4: 8-bit level ~5) and once of a mid-grey
    patch (0.2): the log1p L1 sees the shadow's ~1000x less; the SSIM term of the display images, like
    Table 1's 1-SSIM, sees the two alike (SSIM compares relative changes; its constants damp the darkest)."""
    shadow, grey = _textured(3e-4), _textured(0.2)
    darker = [torch.log1p(torch.expm1(x) * 0.8) for x in (shadow, grey)]
    (l1_shadow, _), (l1_grey, _) = (
        generator_loss(d, x, None, adversarial=False) for d, x in zip(darker, (shadow, grey))
    )
    ssim_shadow, ssim_grey = (display_ssim_loss(d, x) for d, x in zip(darker, (shadow, grey)))
    assert l1_shadow < l1_grey / 100
    assert ssim_grey / 2 < ssim_shadow < ssim_grey * 2
    assert display_ssim_loss(shadow, shadow) == 0


def test_the_ssim_term_has_finite_gradients_on_black_and_blown_out_pixels():
    real = torch.cat([torch.zeros(1, 3, 16, 32), torch.full((1, 3, 16, 32), 3.0)], dim=2)  # log1p: 0 and 19
    fake = (real + 0.01 * torch.randn_like(real)).clamp(min=0).requires_grad_(True)
    albedo = torch.cat([torch.zeros(1, 3, 32, 16), torch.ones(1, 3, 32, 16)], dim=3)
    loss, parts = generator_loss(fake, real, None, adversarial=False, ssim_weight=0.5, linear_scale=albedo + 0.00316)
    loss.backward()
    assert torch.isfinite(fake.grad).all() and fake.grad.abs().sum() > 0
    assert set(parts) == {"l1", "ssim"}
    assert loss.item() == pytest.approx(parts["l1"].item() + 0.5 * parts["ssim"].item(), rel=1e-6)


def test_the_linear_scale_is_what_the_ssim_term_compares():
    """Diffuse values are demodulated: the term compares expm1(.) * (albedo + eps), the display image."""
    real, fake = _textured(0.5, seed=1), _textured(0.5, seed=2)
    albedo = torch.rand(real.shape, generator=torch.Generator().manual_seed(3))
    remodulated = [torch.log1p(torch.expm1(x) * albedo) for x in (fake, real)]
    assert display_ssim_loss(fake, real, albedo).item() == pytest.approx(
        display_ssim_loss(*remodulated).item(), rel=1e-5
    )
    assert display_ssim_loss(fake, real, albedo).item() != pytest.approx(display_ssim_loss(fake, real).item(), rel=1e-2)


def test_critic_loss_is_half_the_negative_wasserstein_estimate_plus_weighted_gp():
    critic = LinearCritic(random_direction((3, 4, 4), 3.0))
    real, fake = torch.rand(4, 3, 4, 4), torch.rand(4, 3, 4, 4)
    loss, parts = critic_loss(critic, real, fake, gp_weight=10.0)
    w_estimate = critic(real).mean() - critic(fake).mean()
    assert parts["wasserstein"].item() == pytest.approx(w_estimate.item(), rel=1e-5)
    assert parts["gp"].item() == pytest.approx(4.0, abs=1e-5)
    assert loss.item() == pytest.approx(-w_estimate.item() / 2 + 40.0, rel=1e-5)


def test_tiny_generator_overfits_fixed_patches_with_l1():
    torch.manual_seed(0)
    g = Generator(ModelSettings(channels=16, blocks=2, cond_channels=8, encoder_channels=16))
    clean = torch.rand(4, 3, 16, 16)
    noisy, features = clean + 0.1 * torch.randn_like(clean), torch.rand(4, 7, 16, 16)
    opt = torch.optim.Adam(g.parameters(), lr=3e-3)
    losses = []
    for _ in range(300):
        loss, _ = generator_loss(g(noisy, features), clean, None, adversarial=False)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 5, f"L1 went from {losses[0]:.4f} to {losses[-1]:.4f} (needs 5x)"


@pytest.mark.parametrize("norm", ["layer", "batch"])
def test_one_wgan_gp_step_on_tiny_nets(norm):
    torch.manual_seed(0)
    g = Generator(ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16))
    d = Critic(ModelSettings(critic_channels=8, critic_norm=norm), patch_size=32)
    opt_g, opt_d = torch.optim.Adam(g.parameters(), 1e-4), torch.optim.Adam(d.parameters(), 1e-4)
    noisy, features, clean = torch.rand(2, 3, 32, 32), torch.rand(2, 7, 32, 32), torch.rand(2, 3, 32, 32)
    d_before = [p.detach().clone() for p in d.parameters()]
    fake = g(noisy, features)
    d_loss, d_parts = critic_loss(d, clean, fake)
    opt_d.zero_grad()
    d_loss.backward()
    opt_d.step()
    assert all(torch.isfinite(v) for v in d_parts.values()) and d_parts["gp"] > 0
    # Every critic weight moves except the last bias: it cancels in D(fake) - D(real) and the GP.
    unchanged = [n for (n, p), b in zip(d.named_parameters(), d_before) if torch.equal(p, b)]
    assert unchanged == ["classifier.2.bias"]
    assert all(p.grad is None for p in g.parameters())  # the critic step leaves G alone
    g_loss, g_parts = generator_loss(fake, clean, d(fake))
    opt_g.zero_grad()
    g_loss.backward()
    opt_g.step()
    assert torch.isfinite(g_loss) and set(g_parts) == {"l1", "adversarial"}
    assert all(p.grad is not None for p in g.parameters())


def test_the_ssim_term_is_float32_and_unchanged_under_bf16_autocast():
    """Its variances blur(x^2) - blur(x)^2 of 8-bit values cancel down to what bf16's 8 bits lose (~250
    levels^2, against SSIM's c2 = 58.5), so under the trainer's autocast it must still run in float32.
    float32's own rounding there is ~0.004 levels^2: the bound below is 1e-5 of a loss near 0.1."""
    real = _textured(0.4, seed=4)
    fake = (real + 0.05 * torch.randn(real.shape, generator=torch.Generator().manual_seed(5))).clamp(min=0)
    albedo = torch.rand(real.shape, generator=torch.Generator().manual_seed(6))
    reference = display_ssim_loss(fake, real, albedo)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = display_ssim_loss(fake, real, albedo)
        assert torch.nn.functional.conv2d(real, torch.ones(3, 3, 1, 1)).dtype == torch.bfloat16  # autocast is on
    assert loss.dtype == torch.float32
    assert loss.item() == pytest.approx(reference.item(), rel=1e-5)


def _pair(size, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(2, 3, size, size, generator=g, dtype=torch.float64)
    return a, (a + 0.1 * torch.randn(a.shape, generator=g, dtype=torch.float64)).clamp(0, 1)


def test_ms_ssim_at_one_scale_is_the_metrics_ssim_and_at_two_the_geometric_mean_of_cs_and_ssim():
    """Below 22 pixels one scale fits the 11x11 window: MS-SSIM is then the SSIM map's mean (metrics'
    constants on 8-bit values, data range 1 here); at 22 the 2x2-averaged image gets a second scale, where the
    full scale keeps only its contrast-structure term."""
    a, b = _pair(16)
    assert ms_ssim(a, b).item() == pytest.approx(metrics.ssim_map_torch(255 * a, 255 * b).mean().item(), abs=1e-12)
    a, b = _pair(22, seed=1)
    c2 = (metrics.SSIM_K2 * 255) ** 2
    full, half = 255 * a, 255 * b
    taps = torch.exp(-0.5 * torch.arange(-5, 6, dtype=torch.float64) ** 2 / 1.5**2)
    taps = (taps / taps.sum()).view(1, 1, 1, -1).expand(3, 1, 1, -1)
    smooth = lambda x: torch.nn.functional.conv2d(  # noqa: E731
        torch.nn.functional.conv2d(x, taps, groups=3), taps.transpose(2, 3), groups=3
    )
    cov = smooth(full * half) - smooth(full) * smooth(half)
    var = smooth(full**2) - smooth(full) ** 2 + smooth(half**2) - smooth(half) ** 2
    cs = ((2 * cov + c2) / (var + c2)).mean(dim=(2, 3))
    pooled = metrics.ssim_map_torch(*(torch.nn.functional.avg_pool2d(x, 2) for x in (full, half))).mean(dim=(2, 3))
    assert ms_ssim(a, b).item() == pytest.approx((cs * pooled).sqrt().mean().item(), abs=1e-12)


def test_the_oidn_losses_are_l1_or_oidns_mix_with_ms_ssim_and_train_finitely():
    """train.oidn_loss: "l1", or OIDN's own 0.16 L1 + 0.84 (1 - MS-SSIM); zero on the target itself, finite
    gradients on flat black and white patches (MS-SSIM's terms there are 1, where a power has no bad slope)."""
    a, b = (x.float() for x in _pair(128))
    l1 = (a - b).abs().mean()
    assert oidn_loss(a, b, "l1").item() == pytest.approx(l1.item(), rel=1e-6)
    mix = 0.16 * l1.item() + 0.84 * (1 - ms_ssim(a, b).item())
    assert oidn_loss(a, b, "l1_msssim").item() == pytest.approx(mix, rel=1e-5)
    assert oidn_loss(b, b, "l1_msssim").item() == pytest.approx(0.0, abs=1e-6)
    for flat in (torch.zeros(1, 3, 128, 128), torch.ones(1, 3, 128, 128)):
        out = flat.clone().requires_grad_()
        oidn_loss(out, torch.rand_like(flat), "l1_msssim").backward()
        assert torch.isfinite(out.grad).all()
    with pytest.raises(ValueError, match="^oidn_loss: 'msssim' is not one of"):
        TrainSettings(oidn_loss="msssim").check()
