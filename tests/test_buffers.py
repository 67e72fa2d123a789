"""The buffer schema: one definition of every layer and one sanitiser. Real EXR files, real arrays."""
import numpy as np
import OpenEXR
import pytest

from admc.common.buffers import BEAUTY, DENOISER_LAYERS, LAYERS, RADIANCE_MAX, VARIANCE_MAX, sanitize
from admc.model.transforms import transform_spec
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
EXR_CHANNELS = {"R", "G", "B", "diffuse.R", "diffuse.G", "diffuse.B", "specular.R", "specular.G", "specular.B",
                "albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth.Z", "coverage.A",
                "diffuse_var.R", "diffuse_var.G", "diffuse_var.B", "specular_var.R", "specular_var.G",
                "specular_var.B"}


def test_every_exr_layer_is_in_the_schema_with_its_channels(tmp_path):
    rng = np.random.default_rng(0)
    layers = {name: rng.uniform(0, 1, (5, 7, len(layer.channels))).astype(np.float32)
              for name, layer in LAYERS.items()}
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
        "diffuse": radiance, "specular": radiance, "albedo": {"nan": 0.0, "min": 0.0, "max": 1.0},
        "normal": {"nan": 0.0, "min": -1.0, "max": 1.0}, "depth": {"nan": 0.0, "min": 0.0, "max": None},
        "coverage": {"nan": 0.0, "min": 0.0, "max": 1.0}}


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


def test_nonfinite_report_flags_negatives_where_the_schema_forbids_them():
    report = nonfinite_report({name: np.full((2, 2, len(layer.channels)), -0.5, np.float32)
                               for name, layer in LAYERS.items()})
    assert set(report) == set(LAYERS) - {"normal"}
