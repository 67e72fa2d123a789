"""The full-image denoiser: exact tiling, transform plumbing, branch selection, hostile inputs (CPU)."""

import numpy as np
import pytest
import torch
from torch import nn

from admc.common.buffers import MISSING_DEPTH
from admc.model.inference.denoiser import LOG_MAX, FullImageDenoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.tiling import (
    CPU_TILE,
    GPU_TILE,
    OPENVINO_TILE,
    axis_windows,
    default_tile,
    receptive_radius,
    run_tiled,
)
from admc.model.nets.generator import Generator, light_within, scaled_kaiming_
from admc.model.nets.settings import ModelSettings
from admc.model.transforms import EPS, diffuse_forward, specular_forward

TINY = ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16)
LOG_TOLERANCE = 1e-5
"""Tiled and untiled convolutions sum the same products in another order (oneDNN picks its kernel by
shape, AVX-512 or AMX): float32 rounding, ~n * 6e-8 relative per conv with fan-in n = 72 here, through
the network's ~10 layers on O(1) log values, stays well under 1e-5 in the log domain."""

# bfloat16 keeps 8 significant bits: unit roundoff u = 2^-8. Under autocast every conv rounds its
# inputs and its output to bf16, ~2u of that layer's output magnitude, and the 0.7-Kaiming test nets
# do not amplify errors, so after the D convs of a generator's chain (D = its receptive radius: every
# conv is 3x3) the output is within 2 * D * u of its magnitude.
BF16_U = 2.0**-8


def log_tolerance(dtype: torch.dtype, magnitude: float) -> float:
    """How far two runs of one network on the same inputs may differ in the log domain (outputs up to
    `magnitude`) when their sums run in another order (tiles, crops, memory layouts: oneDNN picks its
    kernel by shape). float32: LOG_TOLERANCE. bfloat16: the float32 sums inside each conv differ by
    ~1e-6 as in float32, which flips an inner bf16 rounding only rarely, and then by one ulp of one of
    its ~72 summands; the output's own rounding may flip: one bf16 ulp, 2u of the output's magnitude
    (measured: at most 0.33u on the tiling and ensemble tests)."""
    return LOG_TOLERANCE if dtype == torch.float32 else 2 * BF16_U * magnitude


def strong_generator(seed: int, scale: float = 1.0) -> Generator:
    """A random generator with large weights and positive biases: unlike the 0.1-scaled init, pixels
    far out in its receptive field change its output clearly, so a too-small halo shows."""
    torch.manual_seed(seed)
    g = Generator(TINY).eval()
    scaled_kaiming_(g, scale)
    with torch.no_grad():
        for m in g.modules():
            if isinstance(m, nn.Conv2d):
                m.bias.uniform_(0.0, 0.1)
    return g


class PassThrough(nn.Module):
    """A real module that returns its log-domain input: the denoiser must then give back its input."""

    def forward(self, noisy, features):
        return noisy.clone()


class CallCounter(Generator):
    """A generator that counts its forward calls."""

    def __init__(self, config):
        super().__init__(config)
        self.calls = 0
        self.register_forward_hook(lambda *_: setattr(self, "calls", self.calls + 1))


def render_layers(height, width, seed=0, specular=True):
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(height, width, 3)).astype(np.float32)
    layers = {
        "diffuse": rng.gamma(0.5, 2.0, size=(height, width, 3)).astype(np.float32),
        "albedo": rng.random((height, width, 3), dtype=np.float32),
        "normal": normal / np.linalg.norm(normal, axis=-1, keepdims=True),
        "depth": rng.uniform(1.0, 20.0, size=(height, width, 1)).astype(np.float32),
        "coverage": np.ones((height, width, 1), dtype=np.float32),
    }
    if specular:
        layers["specular"] = rng.gamma(0.3, 1.0, size=(height, width, 3)).astype(np.float32)
    return layers


def test_receptive_radius_is_two_per_block_plus_four_and_matches_an_impulse():
    assert receptive_radius(Generator(ModelSettings())) == 36  # paper config: 73x73 field
    g = strong_generator(0)
    radius = receptive_radius(g)
    assert radius == 2 * TINY.blocks + 4
    x, f = torch.rand(1, 3, 41, 41), torch.rand(1, 7, 41, 41)
    for poked in (x, f):  # the image path and the encoder path reach equally far
        with torch.no_grad():
            before = g(x, f)
            poked[0, :, 20, 20] += 1.0
            changed = (g(x, f) - before).abs().amax(dim=1)[0] > 0
        ys, xs = torch.nonzero(changed, as_tuple=True)
        assert (ys - 20).abs().max() == radius and (xs - 20).abs().max() == radius


@pytest.mark.parametrize("size,tile,halo", [(70, 32, 8), (1, 32, 8), (33, 32, 8), (4000, 512, 36), (9, 4, 30)])
def test_axis_windows_cover_the_axis_with_a_full_halo_inside_each_crop(size, tile, halo):
    windows = axis_windows(size, tile, halo)
    assert windows[0][0] == 0 and windows[-1][1] == size
    assert all(a[1] == b[0] for a, b in zip(windows, windows[1:]))
    assert len({c1 - c0 for _, _, c0, c1 in windows}) == 1  # one crop size: tiles can be batched
    for start, end, c0, c1 in windows:
        assert end - start <= tile and 0 <= c0 <= start < end <= c1 <= size
        assert c0 == 0 or start - c0 >= halo
        assert c1 == size or c1 - end >= halo


def test_tiled_equals_untiled_with_the_receptive_halo_and_not_with_less():
    g = strong_generator(1)
    radius = receptive_radius(g)
    x, f = torch.rand(1, 3, 70, 90) * 3, torch.rand(1, 7, 70, 90)
    with torch.no_grad():
        untiled = g(x, f)
        tiled = run_tiled(g, x, f, tile=32, halo=radius)
        short = run_tiled(g, x, f, tile=32, halo=radius - 1)
    scale = untiled.abs().max().item()
    assert scale > 1.0
    assert (tiled - untiled).abs().max().item() <= 1e-5 * scale
    assert (short - untiled).abs().max().item() > 1e-3 * scale  # the check can fail


def test_darkness_gate_keeps_tiles_equal_and_far_pixels_zero():
    """Where no input radiance lies within the receptive radius the output is exactly 0 (the
    positive biases would otherwise paint a tint); the gate looks no farther than the convs, so
    tiles still match the untiled image."""
    g = strong_generator(4)
    radius = receptive_radius(g)
    x, f = torch.zeros(1, 3, 70, 90), torch.rand(1, 7, 70, 90)
    x[..., 30:34, 40:43] = torch.rand(1, 3, 4, 3) * 3
    with torch.no_grad():
        untiled = g(x, f)
        tiled = run_tiled(g, x, f, tile=32, halo=radius)
    near = torch.zeros(70, 90, dtype=torch.bool)
    near[30 - radius : 34 + radius, 40 - radius : 43 + radius] = True
    assert float(untiled[..., ~near].abs().max()) == 0.0
    assert bool((untiled[..., near] != 0).any())  # the check can fail: light nearby is denoised
    assert (tiled - untiled).abs().max().item() <= 1e-5 * untiled.abs().max().item()


@pytest.mark.parametrize("height, width, radius", [(23, 31, 0), (23, 31, 1), (23, 31, 5), (9, 4, 12), (1, 1, 3)])
def test_light_within_is_a_square_window_around_every_lit_pixel(height, width, radius):
    """The gate's dilation against its definition, pixel by pixel: any channel nonzero in the window
    clipped to the image (a window wider than the image included)."""
    rng = np.random.default_rng(height + radius)
    noisy = torch.from_numpy(rng.random((2, 3, height, width), dtype=np.float32))
    dark = rng.random((2, 1, height, width)) > 0.5 / (2 * radius + 1) ** 2  # about half the pixels see light
    noisy[torch.from_numpy(dark).expand(-1, 3, -1, -1)] = 0.0
    noisy[1, 1, 0, 0] = -2.0  # nonzero, not positive: light all the same
    lit = (noisy != 0).any(dim=1)
    expected = torch.zeros(2, 1, height, width, dtype=torch.bool)
    for y in range(height):
        for x in range(width):
            window = lit[:, max(y - radius, 0) : y + radius + 1, max(x - radius, 0) : x + radius + 1]
            expected[:, 0, y, x] = window.flatten(1).any(dim=1)
    assert torch.equal(light_within(noisy, radius), expected)
    assert torch.equal(light_within(noisy.contiguous(memory_format=torch.channels_last), radius), expected)
    assert bool(expected.any()) and not bool(expected.all())  # the check can fail


def test_default_tile_is_by_device_and_at_least_eight_halos():
    assert default_tile(torch.device("cpu"), 12) == CPU_TILE == 320
    assert default_tile(torch.device("cuda"), 12) == GPU_TILE == 512  # a device name: no GPU needed
    assert default_tile(torch.device("cpu"), 116) == 928  # the multi-scale body's halo
    assert default_tile(torch.device("cpu"), 12, "openvino") == OPENVINO_TILE == 640
    assert default_tile(torch.device("cpu"), 116, "openvino") == 928
    assert default_tile(torch.device("cpu"), 12, "onnxruntime") == CPU_TILE
    assert FullImageDenoiser(Generator(TINY), None).tile == CPU_TILE
    assert FullImageDenoiser(Generator(TINY), None, DenoiserOptions(tile=48)).tile == 48


def test_denoiser_tiled_equals_untiled_on_a_70x90_image(inference_dtype):
    # weights at 0.7x Kaiming keep the log outputs O(1), clear of the clamp that would hide errors
    diffuse, specular = strong_generator(2, scale=0.7), strong_generator(3, scale=0.7)
    layers = render_layers(70, 90)
    tiled = FullImageDenoiser(diffuse, specular, DenoiserOptions(tile=32, dtype=inference_dtype))(layers)
    untiled = FullImageDenoiser(diffuse, specular, DenoiserOptions(tile=512, dtype=inference_dtype))(layers)
    assert tiled.tiles == 9 and untiled.tiles == 1
    assert tiled.branches == ("diffuse", "specular")
    albedo = layers["albedo"]
    log_tiled = diffuse_forward(tiled.diffuse, albedo), specular_forward(tiled.specular)
    log_untiled = diffuse_forward(untiled.diffuse, albedo), specular_forward(untiled.specular)
    tolerance = {}
    for a, b, branch in zip(log_tiled, log_untiled, ("diffuse", "specular")):  # the networks' domain
        assert 1.0 < b.max() < LOG_MAX[branch] - 0.1  # nothing clamped
        tolerance[branch] = log_tolerance(inference_dtype, np.abs(b).max())
        assert np.abs(a - b).max() <= tolerance[branch]
    tolerance["image"] = max(tolerance.values())
    # Linear radiance inherits the log-domain difference through the inverse transforms: d/dx of
    # expm1(x) * (albedo + eps) is (linear + albedo + eps), of expm1(x) it is (linear + 1). So a value of
    # 1e-3 on albedo 0.5 may move by ~5e-6: a bound relative to the value alone would be luck.
    gain = {"diffuse": np.abs(untiled.diffuse) + np.clip(albedo, 0, 1) + EPS, "specular": np.abs(untiled.specular) + 1}
    gain["image"] = gain["diffuse"] + gain["specular"]
    for part in ("image", "diffuse", "specular"):
        a, b = getattr(tiled, part), getattr(untiled, part)
        assert a.shape == (70, 90, 3) and a.dtype == np.float32
        rounding = 4 * np.finfo(np.float32).eps * np.abs(b)  # expm1, the product and the sum, in float32
        assert np.all(np.abs(a - b) <= gain[part] * tolerance[part] * (1 + 1e-3) + rounding), part


def test_environment_pixels_keep_their_input(inference_dtype):
    """Coverage 0 (every sample saw the environment): the input is kept, bright or black; the rest
    is denoised."""
    layers = render_layers(20, 24)
    layers["coverage"][:, :8] = 0.0
    layers["diffuse"][:, :4] = 0.7  # a lit environment: kept, not hidden
    layers["diffuse"][:, 4:8] = 0.0  # a black one: stays black
    result = FullImageDenoiser(
        strong_generator(5, scale=0.7), strong_generator(6, scale=0.7), DenoiserOptions(dtype=inference_dtype)
    )(layers)
    # kept pixels never pass through the networks, in either precision: the log value is stored in float32
    # (relative error 2^-24); expm1 scales that by d e^d / (e^d - 1), under 6 for every log value here
    # (d < 5.5), so the radiance comes back within 4e-7
    np.testing.assert_allclose(result.diffuse[:, :8], layers["diffuse"][:, :8], rtol=1e-6, atol=0)
    np.testing.assert_allclose(result.specular[:, :8], layers["specular"][:, :8], rtol=1e-6, atol=0)
    assert np.abs(result.diffuse[:, 8:] - layers["diffuse"][:, 8:]).max() > 0.1  # the check can fail


def test_overlap_below_the_receptive_radius_is_refused():
    g = strong_generator(0)
    with pytest.raises(ValueError, match="receptive field radius 8"):
        FullImageDenoiser(g, None, DenoiserOptions(overlap=7))
    with pytest.raises(ValueError, match="overlap must be given"):
        FullImageDenoiser(PassThrough(), None)


def test_pass_through_network_returns_the_input_radiance(inference_dtype):
    layers = render_layers(37, 23)
    layers["diffuse"][0, 0] = 5000.0  # bright, still within the FP16-safe range
    result = FullImageDenoiser(
        PassThrough(), PassThrough(), DenoiserOptions(tile=16, overlap=0, dtype=inference_dtype)
    )(layers)
    # a copy is no conv: autocast leaves it in float32, and the log transform round trips in float32
    np.testing.assert_allclose(result.diffuse, layers["diffuse"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(result.specular, layers["specular"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(result.image, layers["diffuse"] + layers["specular"], rtol=1e-5, atol=1e-6)
    assert result.sanitized == {}


def test_scene_without_specular_runs_only_the_diffuse_network():
    diffuse, specular = CallCounter(TINY), CallCounter(TINY)
    denoiser = FullImageDenoiser(diffuse, specular, DenoiserOptions(tile=16))
    result = denoiser(render_layers(20, 40, specular=False))
    assert specular.calls == 0 and diffuse.calls == 6  # 2 x 3 tiles
    assert result.branches == ("diffuse",) and result.specular is None
    np.testing.assert_array_equal(result.image, result.diffuse)
    denoiser(render_layers(20, 40))
    assert specular.calls > 0


def test_specular_without_a_specular_network_is_passed_through_and_said(inference_dtype):
    layers = render_layers(12, 12)
    result = FullImageDenoiser(strong_generator(0), None, DenoiserOptions(dtype=inference_dtype))(layers)
    assert result.branches == ("diffuse",) and result.specular_passed_through
    np.testing.assert_array_equal(result.specular, layers["specular"])
    np.testing.assert_allclose(result.image, result.diffuse + layers["specular"], rtol=1e-6)
    assert any("noisy specular" in note for note in result.notes)


def hostile_layers(height, width):
    layers = render_layers(height, width, seed=5)
    layers["diffuse"][0, 0] = 1e6  # firefly beyond FP16
    layers["diffuse"][-1, -1, 1] = np.nan
    layers["specular"][height // 2, width // 2] = np.inf
    layers["albedo"][0, -1] = -0.5
    layers["normal"][-1, 0] = np.nan
    layers["depth"][0, 0] = -np.inf
    return layers


@pytest.mark.parametrize("size", [(1, 1), (127, 129), (3, 200), (70, 90)])
def test_outputs_are_finite_on_hostile_inputs_of_odd_sizes(size, inference_dtype):
    g_d, g_s = strong_generator(6), strong_generator(7)
    layers = hostile_layers(*size)
    result = FullImageDenoiser(g_d, g_s, DenoiserOptions(tile=48, dtype=inference_dtype))(layers)
    assert result.image.shape == (*size, 3)
    for part in (result.image, result.diffuse, result.specular):
        assert np.isfinite(part).all() and (part >= 0).all()
    assert result.sanitized["specular"]["posinf"] == 3
    if size != (1, 1):
        assert result.sanitized["diffuse"] == {"nan": 1, "above_max": 3}
        assert result.sanitized["albedo"]["below_min"] == 3
        assert result.sanitized["normal"]["nan"] == 3
    assert result.network_seconds > 0 and result.seconds >= result.network_seconds


@pytest.mark.parametrize("case", ["black", "white_albedo", "environment_only"])
def test_outputs_are_finite_on_degenerate_scenes(case, inference_dtype):
    layers = render_layers(17, 31, seed=9)
    if case == "black":
        for name in ("diffuse", "specular", "albedo"):
            layers[name][:] = 0.0
    elif case == "white_albedo":
        layers["albedo"][:] = 1.0
    else:
        layers["coverage"][:] = 0.0
        layers["depth"][:] = 0.0
    result = FullImageDenoiser(
        strong_generator(2), strong_generator(3), DenoiserOptions(tile=16, dtype=inference_dtype)
    )(layers)
    assert np.isfinite(result.image).all() and (result.image >= 0).all()
    assert result.sanitized == {}


def test_missing_depth_and_coverage_become_the_environment_depth():
    layers = render_layers(16, 16, specular=False)
    complete = dict(
        layers, depth=np.full((16, 16, 1), MISSING_DEPTH, np.float32), coverage=np.ones((16, 16, 1), np.float32)
    )
    del layers["depth"], layers["coverage"]
    denoiser = FullImageDenoiser(strong_generator(4), None)
    np.testing.assert_array_equal(denoiser(layers).image, denoiser(complete).image)


def test_bad_layers_raise_naming_the_layer():
    denoiser = FullImageDenoiser(strong_generator(0), None)
    layers = render_layers(8, 8)
    with pytest.raises(KeyError, match="albedo"):
        denoiser({k: v for k, v in layers.items() if k != "albedo"})
    with pytest.raises(ValueError, match="'normal' has shape"):
        denoiser(dict(layers, normal=layers["normal"][:4]))


def test_denoiser_follows_the_evaluation_interface():
    denoiser = FullImageDenoiser(strong_generator(0), None)
    assert denoiser.name == "admc" and denoiser.device.startswith("cpu")
    image = denoiser.denoise(render_layers(8, 8, specular=False))
    denoiser.synchronize()
    assert image.shape == (8, 8, 3) and image.dtype == np.float32


def test_bfloat16_autocast_stays_close_to_float32():
    layers = render_layers(20, 20, specular=False)
    generator = strong_generator(2, scale=0.7)
    exact = FullImageDenoiser(generator, None, DenoiserOptions(dtype=torch.float32))(layers)
    low = FullImageDenoiser(generator, None, DenoiserOptions(dtype=torch.bfloat16))(layers)
    log_exact = diffuse_forward(exact.diffuse, layers["albedo"])
    log_low = diffuse_forward(low.diffuse, layers["albedo"])
    error = np.abs(log_low - log_exact).max()
    assert 0 < error < 0.05 * log_exact.max()  # bf16 really ran (not equal), and within its precision
    # measured 0.006-0.013 of the maximum on four seeds; the derived bound is 2 * 8 * 2^-8 = 0.0625
    assert error <= 2 * receptive_radius(generator) * BF16_U * np.abs(log_exact).max()
    assert low.image.dtype == np.float32 and np.isfinite(low.image).all()


def test_bfloat16_tiles_equal_the_untiled_image_up_to_one_bf16_rounding():
    """With the full halo every output pixel sees the same inputs in a tile as in the whole image;
    only a changed float32 accumulation order inside a kernel could flip one bf16 rounding of the
    result, 2u of the output magnitude. One pixel less of halo breaks that bound."""
    g = strong_generator(1).to(memory_format=torch.channels_last)
    radius = receptive_radius(g)
    x = (torch.rand(1, 3, 70, 90) * 3).contiguous(memory_format=torch.channels_last)
    f = torch.rand(1, 7, 70, 90).contiguous(memory_format=torch.channels_last)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        untiled = g(x, f).float()
        tiled = run_tiled(g, x, f, tile=32, halo=radius)
        short = run_tiled(g, x, f, tile=32, halo=radius - 1)
    bound = 2 * BF16_U * untiled.abs().max().item()
    assert untiled.abs().max().item() > 1.0
    assert (tiled - untiled).abs().max().item() <= bound
    assert (short - untiled).abs().max().item() > bound  # measured 2.9x the bound: the check can fail


class FeatureEcho(nn.Module):
    """A generator stand-in that records the features it is called with and passes its input through."""

    def __init__(self, noise_input: bool):
        super().__init__()
        self.config = ModelSettings(noise_input=noise_input)
        self.seen = []

    def forward(self, noisy, features):
        self.seen.append(features.clone())
        return noisy.clone()


def with_variance(layers, seed=3):
    rng = np.random.default_rng(seed)
    height, width = layers["diffuse"].shape[:2]
    return {
        **layers,
        "diffuse_var": rng.random((height, width, 3), dtype=np.float32) * 0.1,
        "specular_var": rng.random((height, width, 3), dtype=np.float32) * 0.1,
    }


@pytest.mark.parametrize("normalize_exposure", [False, True])
def test_noise_input_weights_read_each_branchs_variance_as_its_noise_map(normalize_exposure):
    from admc.model.transforms import diffuse_noise, specular_noise

    layers = with_variance(render_layers(12, 10))
    if normalize_exposure:  # a dim image: the networks see the radiance times a gain, its variance times gain^2
        layers = {
            k: v * (1e-3 if k in ("diffuse", "specular") else 1e-6 if k.endswith("_var") else 1)
            for k, v in layers.items()
        }
    diffuse, specular = FeatureEcho(noise_input=True), FeatureEcho(noise_input=True)
    denoiser = FullImageDenoiser(diffuse, specular, DenoiserOptions(overlap=0, normalize_exposure=normalize_exposure))
    gain = np.float32(denoiser(layers).exposure_gain)
    assert (gain > 1) == normalize_exposure
    (d,), (s,) = diffuse.seen, specular.seen
    assert d.shape == s.shape == (1, 8, 12, 10)
    torch.testing.assert_close(d[0, :7], s[0, :7])
    want_d = diffuse_noise(layers["diffuse_var"] * gain**2, layers["diffuse"] * gain, layers["albedo"])
    want_s = specular_noise(layers["specular_var"] * gain**2, layers["specular"] * gain)
    np.testing.assert_array_equal(d[0, 7].numpy(), want_d[..., 0])
    np.testing.assert_array_equal(s[0, 7].numpy(), want_s[..., 0])

    plain = FeatureEcho(noise_input=False)
    FullImageDenoiser(plain, None, DenoiserOptions(overlap=0))(layers)
    assert plain.seen[0].shape[1] == 7  # weights without the noise input never see it


def test_noise_input_weights_name_the_variance_layers_an_input_lacks():
    denoiser = FullImageDenoiser(FeatureEcho(True), FeatureEcho(True), DenoiserOptions(overlap=0, source="w.pt"))
    layers = render_layers(8, 8)
    assert denoiser.missing_layers(layers) == ["diffuse_var", "specular_var"]
    assert denoiser.missing_layers({k: v for k, v in layers.items() if k != "specular"}) == ["diffuse_var"]
    with pytest.raises(KeyError, match="lacks layer.s. diffuse_var, specular_var, which w.pt read"):
        denoiser(layers)
    layers["diffuse_var"] = np.full((8, 8, 3), np.nan, np.float32)
    layers["specular_var"] = np.zeros((8, 8, 3), np.float32)
    result = denoiser(layers)  # a NaN variance is repaired like any layer, and said
    assert result.sanitized["diffuse_var"] == {"nan": 8 * 8 * 3} and np.isfinite(result.image).all()
    with pytest.raises(ValueError, match="'specular_var' has shape"):
        denoiser(dict(layers, specular_var=layers["specular_var"][:4]))


def test_weights_without_the_noise_input_ignore_variance_layers_bit_for_bit():
    """The default (model.noise_input = false) computes what it did before the input existed, whatever
    variance layers (broken ones included) the input carries, and reports no repair of them."""
    layers = render_layers(24, 20)
    broken = {**with_variance(layers), "diffuse_var": np.full((3, 3, 3), np.nan, np.float32)}
    denoiser = FullImageDenoiser(strong_generator(0), strong_generator(1), DenoiserOptions(tile=16, dark_pass=True))
    a, b = denoiser(layers), denoiser(broken)
    np.testing.assert_array_equal(a.image, b.image)
    assert a.sanitized == b.sanitized == {}


def noise_generator(seed: int, scale: float = 1.0, input_skip: bool = False) -> Generator:
    """strong_generator with the noise input: its encoder's weights on the noise channel are as large as the others'."""
    torch.manual_seed(seed)
    g = Generator(ModelSettings(**{**TINY.__dict__, "noise_input": True, "input_skip": input_skip})).eval()
    scaled_kaiming_(g, scale)
    with torch.no_grad():
        for m in g.modules():
            if isinstance(m, nn.Conv2d):
                m.bias.uniform_(0.0, 0.1 * scale)
    return g


def test_noise_input_weights_tile_and_run_the_dark_pass_and_ensemble_like_the_whole_image(inference_dtype):
    layers = with_variance(render_layers(40, 36))
    for name in ("diffuse", "specular"):  # a dark band: the dark pass runs there, at 64x the exposure
        layers[name][:, :12] *= 1e-4
        layers[f"{name}_var"][:, :12] *= 1e-8
    # 0.7x Kaiming keeps the log outputs O(1), where log_tolerance's float32 bound holds (as on the 70x90 test)
    strong = noise_generator(0, 0.7), noise_generator(1, 0.7)
    near_identity = noise_generator(0, 0.1, input_skip=True), noise_generator(1, 0.1, input_skip=True)
    for generators, options in ((strong, {}), (strong, {"ensemble": 4}), (near_identity, {"dark_pass": True})):
        whole = FullImageDenoiser(*generators, DenoiserOptions(tile=64, dtype=inference_dtype, **options))(layers)
        tiled = FullImageDenoiser(*generators, DenoiserOptions(tile=16, dtype=inference_dtype, **options))(layers)
        assert tiled.tiles > 1 == whole.tiles
        albedo = layers["albedo"]
        for a, b, branch in (
            (diffuse_forward(tiled.diffuse, albedo), diffuse_forward(whole.diffuse, albedo), "diffuse"),
            (specular_forward(tiled.specular), specular_forward(whole.specular), "specular"),
        ):
            assert b.max() < LOG_MAX[branch] - 0.1  # nothing clamped
            assert np.abs(a - b).max() <= log_tolerance(inference_dtype, float(np.abs(b).max()))
        assert whole.dark_share > 0 if options.get("dark_pass") else whole.dark_share == 0
    # the map matters: other variances, another output
    quieter = {**layers, "diffuse_var": layers["diffuse_var"] * 1e-4}
    plain = FullImageDenoiser(*strong, DenoiserOptions(tile=64, dtype=inference_dtype))
    assert np.abs(plain(quieter).diffuse - plain(layers).diffuse).max() > 0


class NonFiniteAt(nn.Module):
    """A real module that returns its input with a NaN, +inf and -inf at three pixels."""

    def forward(self, noisy, features):
        out = noisy.clone()
        out[0, 0, 1, 1], out[0, 1, 2, 3], out[0, 2, 4, 5] = float("nan"), float("inf"), float("-inf")
        return out


def test_non_finite_network_outputs_are_counted_and_set_to_zero():
    layers = render_layers(8, 10, seed=6)
    result = FullImageDenoiser(
        NonFiniteAt(), NonFiniteAt(), DenoiserOptions(overlap=0, dtype=torch.float32, normalize_exposure=False)
    )(layers)
    assert result.nonfinite_outputs == 6 and np.isfinite(result.image).all()
    assert result.diffuse[1, 1, 0] == 0 and result.specular[2, 3, 1] == 0  # log 0 -> 0 radiance
    assert result.specular[4, 5, 2] == 0


def test_an_oidn_blend_mixes_each_branch_with_oidns_own_output_at_its_share():
    """train.oidn_blend's shares at inference: each branch's output is share * admc + (1 - share) * OIDN's
    per-branch output (oidn_bases at high, on the same sanitised input); the image is their sum. A refiner,
    whose output already starts from OIDN's, takes no blend."""
    from admc.model.inference.denoiser import sanitize_layers
    from admc.model.inference.oidn_base import oidn_bases

    layers = render_layers(40, 48, seed=5)
    diffuse, specular = strong_generator(1), strong_generator(2)
    plain = FullImageDenoiser(diffuse, specular, DenoiserOptions(dtype=torch.float32))(layers)
    shares = {"diffuse": 0.25, "specular": 0.6}
    blended = FullImageDenoiser(diffuse, specular, DenoiserOptions(dtype=torch.float32, oidn_blend=shares))(layers)
    oidn = oidn_bases(sanitize_layers(layers)[0], "oidn")
    for branch, share in shares.items():  # float32 arithmetic on values of order 1-10: a few ulps
        want = share * getattr(plain, branch) + (1 - share) * oidn[branch]
        np.testing.assert_allclose(getattr(blended, branch), want, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(blended.image, blended.diffuse + blended.specular, rtol=1e-6, atol=1e-6)
    assert "blended with OIDN" in FullImageDenoiser(diffuse, specular, DenoiserOptions(oidn_blend=shares)).device
    refiner_settings = ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16, base="oidn")
    with pytest.raises(ValueError, match="refiner"):
        FullImageDenoiser(Generator(refiner_settings), None, DenoiserOptions(oidn_blend=shares))
