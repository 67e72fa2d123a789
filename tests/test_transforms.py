"""Transforms: exact values on hand-picked inputs, and properties over extreme inputs (hypothesis).

Round-trip tolerance: a stored log value d is off by at most half an FP16 ulp, delta = ulp16(d)/2
(<= 2**-11 * d). Through expm1 and the albedo factor A = albedo + eps that becomes
|x' - x| <= (x + A) * (exp(delta) - 1): a relative error of about delta, i.e. <= 0.8 % at the
radiance maximum (d <= 16.9) and ~0.05 % for radiance near 1.
"""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from admc.common.buffers import VARIANCE_MAX, sanitize
from admc.model import transforms as T

EXTREMES = [0.0, 1e-8, 1e-3, 0.5, 1.0, 7.0, 1e4, 65504.0, 7e4, 1e9, 3e38, -1e-8, -5.0, -1e9, np.nan, np.inf, -np.inf]
SHAPE = (3, 4, 3)

radiance = arrays(
    np.float32,
    SHAPE,
    elements=st.one_of(st.sampled_from(EXTREMES), st.floats(width=32, allow_nan=True, allow_infinity=True)),
)
albedo_values = arrays(
    np.float32,
    SHAPE,
    elements=st.one_of(st.sampled_from([0.0, 1.0, 0.5, 1e-8, 2.0, -1.0, np.nan, np.inf]), st.floats(0, 1, width=32)),
)


def _fp16_delta(d: np.ndarray) -> np.ndarray:
    """Half an FP16 ulp at each stored value (plus a float32 ulp for the forward's own rounding)."""
    d16 = np.abs(d.astype(np.float16))
    return np.spacing(d16).astype(np.float64) / 2 + np.spacing(np.abs(d)).astype(np.float64)


def _assert_storable(x16: np.ndarray, n_clamped: int) -> None:
    assert x16.dtype == np.float16
    assert np.isfinite(x16).all()
    assert np.abs(x16.astype(np.float32)).max() <= T.FP16_MAX
    assert n_clamped == 0  # the log domain never needs the clamp


def test_forward_refuses_unsanitized_input():
    with pytest.raises(ValueError, match=r"diffuse has 1 non-finite.*sanitize"):
        T.diffuse_forward(np.array([np.nan, 1.0]), np.ones(2))
    with pytest.raises(ValueError, match="specular has 1"):
        T.specular_forward(np.array([np.inf]))


@pytest.mark.parametrize("layout", ["contiguous", "flipped", "channels_first", "scalar"])
def test_log_transforms_match_numpy_on_any_layout(layout):
    """log1p / expm1 run in place through torch: on views, transposed layouts and 0-d input they give
    NumPy's float32 result within 4 float32 epsilons (each library rounds the function to about 1 ulp,
    the albedo product rounds once more) and leave the caller's arrays as they were."""
    rng = np.random.default_rng(3)
    linear, albedo = rng.gamma(0.5, 2.0, (4, 6, 3)).astype(np.float32), rng.random((4, 6, 3), dtype=np.float32)
    views = {
        "contiguous": lambda a: a,
        "flipped": lambda a: a[::-1, ::2],
        "channels_first": lambda a: np.ascontiguousarray(a.transpose(2, 0, 1)).transpose(1, 2, 0),
        "scalar": lambda a: a[1, 2, 0],
    }
    x, a = views[layout](linear), views[layout](albedo)
    before = (np.copy(x), np.copy(a))
    a32 = np.clip(a, 0, 1) + np.float32(T.EPS)
    pairs = [
        (T.diffuse_forward(x, a), np.log1p(x / a32)),
        (T.specular_forward(x), np.log1p(x)),
        (T.diffuse_inverse(x, a), np.expm1(x) * a32),
        (T.specular_inverse(x), np.expm1(x)),
    ]
    for got, want in pairs:
        np.testing.assert_allclose(got, want, rtol=4 * np.finfo(np.float32).eps, atol=0)
    np.testing.assert_array_equal(x, before[0])
    np.testing.assert_array_equal(a, before[1])


def test_diffuse_known_values_zero_and_white_albedo():
    d = T.diffuse_forward(np.array([1.0, 1.0, 0.0, -3.0]), np.array([0.0, 1.0, 0.5, 0.5]))
    np.testing.assert_allclose(d, [np.log1p(1 / T.EPS), np.log1p(1 / (1 + T.EPS)), 0.0, 0.0], rtol=1e-6)
    np.testing.assert_allclose(T.diffuse_inverse(d, np.array([0.0, 1.0, 0.5, 0.5])), [1, 1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(T.specular_inverse(T.specular_forward(np.array([0.0, 2.5]))), [0.0, 2.5], rtol=1e-6)


@settings(max_examples=150, deadline=None)
@given(x=radiance, a=albedo_values)
def test_diffuse_roundtrip_through_fp16(x, a):
    clean, _ = sanitize(x, "diffuse")
    alb, _ = sanitize(a, "albedo")
    d = T.diffuse_forward(clean, alb)
    d16, n_clamped = T.to_fp16(d)
    _assert_storable(d16, n_clamped)
    back = T.diffuse_inverse(d16.astype(np.float32), alb).astype(np.float64)
    amp = np.clip(alb, 0, 1).astype(np.float64) + T.EPS
    tol = (clean + amp) * np.expm1(_fp16_delta(d)) + 1e-12
    assert np.isfinite(back).all()
    assert (np.abs(back - clean) <= tol).all(), np.abs(back - clean).max()


@settings(max_examples=150, deadline=None)
@given(x=radiance)
def test_specular_roundtrip_through_fp16(x):
    clean, _ = sanitize(x, "specular")
    s16, n_clamped = T.to_fp16(T.specular_forward(clean))
    _assert_storable(s16, n_clamped)
    back = T.specular_inverse(s16.astype(np.float32)).astype(np.float64)
    tol = (clean + 1.0) * np.expm1(_fp16_delta(T.specular_forward(clean))) + 1e-12
    assert (np.abs(back - clean) <= tol).all()


anything = st.one_of(st.sampled_from(EXTREMES), st.floats(width=32, allow_nan=True, allow_infinity=True))


@settings(max_examples=150, deadline=None)
@given(
    n=arrays(np.float32, SHAPE, elements=anything),
    z=arrays(np.float32, (3, 4, 1), elements=anything),
    a=arrays(np.float32, SHAPE, elements=anything),
    c=arrays(np.float32, (3, 4, 1), elements=st.sampled_from([0.0, 0.25, 1.0, np.nan])),
)
def test_features_always_in_unit_range(n, z, a, c):
    f = T.features(n, z, a, c)
    assert f.shape == (3, 4, 7) and f.dtype == np.float32
    assert np.isfinite(f).all()
    assert f.min() >= 0.0 and f.max() <= 1.0
    f16, n_clamped = T.to_fp16(f)
    assert n_clamped == 0 and np.isfinite(f16).all()


def test_features_channel_order_and_depth_rule():
    normal = np.zeros((2, 2, 3), np.float32)
    normal[..., 0] = -1.0
    normal[..., 2] = 1.0
    normal[0, 0, 1] = np.nan
    depth = np.array([[[2.0], [8.0]], [[100.0], [np.inf]]], np.float32)
    coverage = np.array([[[1.0], [0.5]], [[0.0], [1.0]]], np.float32)  # 100 is environment: ignored
    albedo = np.full((2, 2, 3), 0.25, np.float32)
    f = T.features(normal, depth, albedo, coverage)
    np.testing.assert_array_equal(f[..., 0], 0.0)
    np.testing.assert_array_equal(f[..., 1], 0.5)  # NaN -> 0 -> 0.5
    np.testing.assert_array_equal(f[..., 2], 1.0)
    np.testing.assert_allclose(f[..., 3], [[0.25, 1.0], [1.0, 1.0]])
    np.testing.assert_array_equal(f[..., 4:], 0.25)


def test_depth_without_hits_is_far():
    z = np.full((4, 4, 1), 3.0, np.float32)
    np.testing.assert_array_equal(T.depth_forward(z, np.zeros_like(z)), 1.0)


def test_to_fp16_clamps_and_counts_never_inf():
    x16, n = T.to_fp16(np.array([1e9, -np.inf, np.inf, 3.0, -65504.0], np.float32))
    np.testing.assert_array_equal(x16.astype(np.float32), [65504, -65504, 65504, 3, -65504])
    assert n == 3
    with pytest.raises(ValueError, match="NaN"):
        T.to_fp16(np.array([np.nan]))


def test_transform_spec_is_json_and_names_parameters():
    spec = T.transform_spec()
    assert json.loads(json.dumps(spec)) == spec
    assert spec["eps"] == T.EPS == 0.00316
    assert spec["feature_channels"] == ["normal.X", "normal.Y", "normal.Z", "depth", "albedo.R", "albedo.G", "albedo.B"]


def test_feature_layout_slices_name_the_channels_transforms_writes():
    """The named slices of admc.common.layout pick the buffers `features` concatenates."""
    from admc.common.layout import ALBEDO, DEPTH, FEATURE_CHANNELS, N_FEATURES, NORMAL

    rng = np.random.default_rng(0)
    normal, albedo = rng.uniform(-1, 1, (4, 5, 3)), rng.uniform(0, 1, (4, 5, 3))
    depth, coverage = rng.uniform(1, 2, (4, 5, 1)), np.ones((4, 5, 1))
    f = T.features(normal, depth, albedo, coverage)
    assert f.shape[-1] == N_FEATURES == len(FEATURE_CHANNELS)
    np.testing.assert_array_equal(f[..., NORMAL], T.normal_forward(normal))
    np.testing.assert_array_equal(f[..., DEPTH], T.depth_forward(depth, coverage))
    np.testing.assert_array_equal(f[..., ALBEDO], T.albedo_forward(albedo))
    assert [FEATURE_CHANNELS[s][0].split(".")[0] for s in (NORMAL, DEPTH, ALBEDO)] == ["normal", "depth", "albedo"]


def test_noise_level_is_the_log_domain_std_of_a_pixel_mean():
    """The delta method, checked by sampling: the std of log1p(mean / s) over many renders of a pixel."""
    rng = np.random.default_rng(0)
    radiance, scale, spp = 0.4, 0.25, 64
    samples = rng.exponential(radiance, size=(20000, spp))  # a skewed per-sample distribution, mean = radiance
    means = samples.mean(axis=1)
    empirical = np.log1p(means / scale).std()
    variance = np.full((1, 1, 3), samples.var(axis=1, ddof=1).mean() / spp)
    level = T.noise_forward(variance, np.full((1, 1, 3), radiance), scale)
    assert level.shape == (1, 1, 1) and level.dtype == np.float32
    std = np.expm1(level[0, 0, 0] * np.log1p(1 / T.NOISE_STD_UNIT)) * T.NOISE_STD_UNIT
    assert std == pytest.approx(empirical, rel=0.03)  # 20000 draws: ~1% sampling error


def test_noise_maps_of_the_two_branches_use_their_own_log_domains():
    var = np.array([[[0.04, 0.09, 0.16]]])
    x = np.array([[[1.0, 2.0, 3.0]]])
    albedo = np.array([[[0.5, 0.0, 1.0]]])
    diffuse = np.sqrt(var) / (x + np.clip(albedo, 0, 1) + T.EPS)
    specular = np.sqrt(var) / (x + 1.0)
    unit = T.NOISE_STD_UNIT
    assert T.diffuse_noise(var, x, albedo)[0, 0, 0] == pytest.approx(
        np.log1p(diffuse.mean() / unit) / np.log1p(1 / unit), rel=1e-6
    )
    assert T.specular_noise(var, x)[0, 0, 0] == pytest.approx(
        np.log1p(specular.mean() / unit) / np.log1p(1 / unit), rel=1e-6
    )
    assert T.specular_noise(np.zeros_like(var), x)[0, 0, 0] == 0.0  # converged: nothing left to remove
    one = T.specular_noise(np.full((1, 1, 3), 4.0), np.ones((1, 1, 3)))  # std 2 / (1 + 1) = 1
    assert one[0, 0, 0] == pytest.approx(1.0, rel=1e-6)


def test_noise_map_and_variance_sanitizing_stay_finite_on_hostile_values():
    var = np.array([[[np.nan, np.inf, -np.inf], [-1.0, 1e30, 0.5]]], dtype=np.float32)
    x = np.array([[[np.nan, np.inf, 0.0], [1e30, -1.0, 0.0]]], dtype=np.float32)
    level = T.specular_noise(var, x)
    assert np.isfinite(level).all() and (level >= 0).all()
    clean, counts = sanitize(var, "specular_var")
    assert counts == {"nan": 1, "posinf": 1, "neginf": 1, "below_min": 1, "above_max": 1}
    assert clean.tolist() == [[[0.0, VARIANCE_MAX, 0.0], [0.0, VARIANCE_MAX, 0.5]]]
