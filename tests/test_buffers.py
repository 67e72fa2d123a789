"""The buffer schema and the OIDN adapter: one definition of every layer, one sanitiser, one OIDN call.

Real EXR files, real pyoidn, real arrays. The adapter is compared with pyoidn called directly on the
same bits: the same library call on the same input is deterministic, so equality is exact.
"""

import numpy as np
import OpenEXR
import pyoidn
import pytest

from admc.common import oidn
from admc.common.buffers import BEAUTY, DENOISER_LAYERS, LAYERS, RADIANCE_MAX, VARIANCE_MAX, sanitize
from admc.common.layout import BASE_QUALITIES
from admc.model.inference.oidn_base import oidn_bases
from admc.model.transforms import transform_spec
from admc.pipeline.evaluation.baselines import OidnDenoiser
from admc.pipeline.render.integrator import aov_layout
from admc.stores.exr import ExrError, nonfinite_report, read_exr, write_exr

INF, NAN = np.inf, np.nan
PROBE = np.array([NAN, INF, -INF, -2.0, 0.5, 1e10], np.float32)
# What each layer makes of PROBE: NaN, +Inf, -Inf, below every range, inside, above every bounded range.
EXPECTED = {
    BEAUTY: [0.0, 0.0, 0.0, 0.0, 0.5, 1e10],
    "diffuse": [0.0, RADIANCE_MAX, 0.0, 0.0, 0.5, RADIANCE_MAX],
    "specular": [0.0, RADIANCE_MAX, 0.0, 0.0, 0.5, RADIANCE_MAX],
    "albedo": [0.0, 1.0, 0.0, 0.0, 0.5, 1.0],
    "normal": [0.0, 1.0, -1.0, -1.0, 0.5, 1.0],
    "depth": [0.0, 0.0, 0.0, 0.0, 0.5, 1e10],
    "coverage": [0.0, 1.0, 0.0, 0.0, 0.5, 1.0],
    "diffuse_var": [0.0, VARIANCE_MAX, 0.0, 0.0, 0.5, VARIANCE_MAX],
    "specular_var": [0.0, VARIANCE_MAX, 0.0, 0.0, 0.5, VARIANCE_MAX],
}
# The channels of an admc EXR: the file format users' renders and our outputs share.
EXR_CHANNELS = {
    "R",
    "G",
    "B",
    "diffuse.R",
    "diffuse.G",
    "diffuse.B",
    "specular.R",
    "specular.G",
    "specular.B",
    "albedo.R",
    "albedo.G",
    "albedo.B",
    "normal.X",
    "normal.Y",
    "normal.Z",
    "depth.Z",
    "coverage.A",
    "diffuse_var.R",
    "diffuse_var.G",
    "diffuse_var.B",
    "specular_var.R",
    "specular_var.G",
    "specular_var.B",
}


def test_every_exr_layer_is_in_the_schema_with_its_channels(tmp_path):
    rng = np.random.default_rng(0)
    layers = {name: rng.uniform(0, 1, (5, 7, len(layer.channels))).astype(np.float32) for name, layer in LAYERS.items()}
    write_exr(tmp_path / "all.exr", layers, precision="float")
    written = {c.name for c in OpenEXR.File(str(tmp_path / "all.exr")).header()["channels"]}
    assert written == EXR_CHANNELS
    back = read_exr(tmp_path / "all.exr")
    assert set(back) == set(LAYERS)
    for name, array in layers.items():
        np.testing.assert_array_equal(back[name], array)
    with pytest.raises(ExrError, match="unknown layer 'variance'"):
        write_exr(tmp_path / "bad.exr", {"variance": layers["diffuse"]})


def test_the_renderer_and_the_denoiser_use_the_schema_channels():
    for name, channels in aov_layout(split=True):
        if name in LAYERS:
            assert channels == LAYERS[name].channels, name
    assert {name for name, _ in aov_layout(split=True)} >= set(DENOISER_LAYERS)
    assert set(DENOISER_LAYERS) <= set(LAYERS)


def test_the_transform_spec_keeps_the_rules_the_shipped_weights_were_trained_with():
    """Weights and patch stores record these rules and are refused when they change."""
    radiance = {"nan": 0.0, "min": 0.0, "max": 65504.0}
    assert transform_spec()["sanitize"] == {
        "diffuse": radiance,
        "specular": radiance,
        "albedo": {"nan": 0.0, "min": 0.0, "max": 1.0},
        "normal": {"nan": 0.0, "min": -1.0, "max": 1.0},
        "depth": {"nan": 0.0, "min": 0.0, "max": None},
        "coverage": {"nan": 0.0, "min": 0.0, "max": 1.0},
    }


@pytest.mark.parametrize("name", list(LAYERS))
def test_sanitize_applies_each_layers_rule_and_counts_each_case(name):
    assert set(EXPECTED) == set(LAYERS)  # a new layer needs its expected rule here
    probe = PROBE.copy()
    clean, counts = sanitize(probe, name)
    assert clean.dtype == np.float32
    np.testing.assert_array_equal(clean, np.float32(EXPECTED[name]))
    np.testing.assert_array_equal(probe, PROBE, err_msg="the input is left as it was")
    bounded = LAYERS[name].high is not None
    assert counts == {"nan": 1, "posinf": 1, "neginf": 1, "below_min": 1, "above_max": int(bounded)}


def test_sanitize_keeps_valid_values_and_refuses_unknown_layers():
    inside = np.float32([[0.0, 0.25, 1.0]])
    for name in LAYERS:
        clean, counts = sanitize(inside, name)
        np.testing.assert_array_equal(clean, inside)
        assert not any(counts.values()), name
    with pytest.raises(ValueError, match="unknown buffer 'ref_diffuse'"):
        sanitize(inside, "ref_diffuse")


@pytest.mark.parametrize("name", list(LAYERS))
def test_one_bad_value_in_a_clean_layer_is_repaired_as_in_a_dirty_one(name):
    """A clean layer takes a shortcut (its min and max checked, then copied): a single NaN, Inf or
    out-of-range value anywhere must still take the full rule, and the clean result is a copy."""
    clean_layer = np.full((7, 5, 3), 0.5, np.float32)
    for position, value in enumerate(PROBE):
        if value == 0.5:
            continue
        layer = clean_layer.copy()
        layer[3, 2, 1] = value
        repaired, counts = sanitize(layer, name)
        expected = clean_layer.copy()
        expected[3, 2, 1] = EXPECTED[name][position]
        np.testing.assert_array_equal(repaired, expected, err_msg=f"{name}: {value}")
        assert sum(counts.values()) == (value != 1e10 or LAYERS[name].high is not None), (name, value, counts)
    repaired, counts = sanitize(clean_layer, name)
    np.testing.assert_array_equal(repaired, clean_layer)
    assert not any(counts.values())
    repaired[0, 0, 0] = 2.0
    assert clean_layer[0, 0, 0] == 0.5, "the result is a new array, never the input"


def test_nonfinite_report_flags_negatives_where_the_schema_forbids_them():
    report = nonfinite_report(
        {name: np.full((2, 2, len(layer.channels)), -0.5, np.float32) for name, layer in LAYERS.items()}
    )
    assert set(report) == set(LAYERS) - {"normal"}


def _image(rng, h=24, w=20):
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return {
        "diffuse": rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32),
        "specular": rng.gamma(0.5, 0.2, (h, w, 3)).astype(np.float32),
        "albedo": rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
        "normal": normal,
    }


@pytest.mark.parametrize("quality", oidn.QUALITIES)
def test_oidn_adapter_passes_its_quality_to_pyoidn(quality):
    layers = _image(np.random.default_rng(1))
    guided = oidn.denoise(layers["diffuse"], layers["albedo"], layers["normal"], quality=quality)
    np.testing.assert_array_equal(
        guided, pyoidn.denoise(layers["diffuse"], layers["albedo"], layers["normal"], hdr=True, quality=quality)
    )
    alone = oidn.denoise(layers["specular"], quality=quality)
    np.testing.assert_array_equal(alone, pyoidn.denoise(layers["specular"], hdr=True, quality=quality))


def test_oidn_qualities_differ_and_unknown_ones_are_refused():
    """Without the first, the pass-through test could not tell a dropped quality from a kept one."""
    layers = _image(np.random.default_rng(2))
    fast = oidn.denoise(layers["diffuse"], layers["albedo"], layers["normal"], quality="fast")
    high = oidn.denoise(layers["diffuse"], layers["albedo"], layers["normal"], quality="high")
    assert not np.array_equal(fast, high)
    with pytest.raises(ValueError, match="OIDN quality must be one of high, balanced, fast, got 'default'"):
        oidn.denoise(layers["diffuse"], quality="default")
    with pytest.raises(ValueError, match="got 'best'"):
        OidnDenoiser(quality="best")


@pytest.mark.parametrize("quality", ["fast", "high"])
def test_the_oidn_baseline_runs_at_its_quality_on_the_sanitised_beauty(quality):
    layers = _image(np.random.default_rng(3))
    layers["diffuse"][0, 0] = [NAN, INF, -1.0]
    layers["specular"][0, 0, 2] = 0.25
    layers["albedo"][1, 1] = [NAN, 2.0, -0.5]
    image = OidnDenoiser(quality=quality).denoise(layers)
    colour = layers["diffuse"] + layers["specular"]
    colour[0, 0] = [0.0, 0.0, 0.0]  # NaN, +Inf and the negative sum become 0 in the beauty
    albedo = layers["albedo"].copy()
    albedo[1, 1] = [0.0, 1.0, 0.0]
    np.testing.assert_array_equal(image, pyoidn.denoise(colour, albedo, layers["normal"], hdr=True, quality=quality))


@pytest.mark.parametrize("base", sorted(BASE_QUALITIES))
def test_the_refiners_bases_are_oidn_at_the_qualities_their_base_names(base):
    quality = BASE_QUALITIES[base]
    layers = _image(np.random.default_rng(4))
    bases = oidn_bases(layers, base)
    diffuse = pyoidn.denoise(
        layers["diffuse"], layers["albedo"], layers["normal"], hdr=True, quality=quality["diffuse"]
    )
    specular = pyoidn.denoise(layers["specular"], hdr=True, quality=quality["specular"])
    np.testing.assert_array_equal(bases["diffuse"], np.maximum(diffuse, 0.0))
    np.testing.assert_array_equal(bases["specular"], np.maximum(specular, 0.0))


def test_the_fast_refiner_base_differs_from_the_high_one_on_the_specular_branch_only():
    layers = _image(np.random.default_rng(4))
    high, fast = oidn_bases(layers, "oidn"), oidn_bases(layers, "oidn-fast")
    np.testing.assert_array_equal(high["diffuse"], fast["diffuse"])
    assert not np.array_equal(high["specular"], fast["specular"])
