"""Reading users' EXRs for `denoise` (both layouts, every error) and writing the result, with real files."""

import numpy as np
import OpenEXR
import pytest
import torch

from admc.model.inference.denoiser import FullImageDenoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.nets.generator import Generator
from admc.model.nets.settings import ModelSettings
from admc.pipeline.stages.denoise import DenoiseInputError, load_denoise_input, write_denoised
from admc.stores.exr import ExrError, read_exr, write_exr

TINY = ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16)
H, W = 24, 40


@pytest.fixture(scope="module")
def denoiser():
    torch.manual_seed(0)
    return FullImageDenoiser(Generator(TINY), Generator(TINY), DenoiserOptions(tile=16))


def buffers(seed=0):
    rng = np.random.default_rng(seed)
    return {
        "diffuse": rng.gamma(0.5, 2.0, size=(H, W, 3)).astype(np.float32),
        "specular": rng.gamma(0.3, 1.0, size=(H, W, 3)).astype(np.float32),
        "albedo": rng.random((H, W, 3), dtype=np.float32),
        "normal": (np.abs(rng.uniform(-1, 1, size=(H, W, 3))) * [1, -1, 1]).astype(np.float32),  # facing the camera
        "depth": rng.uniform(1, 9, size=(H, W, 1)).astype(np.float32),
        "coverage": np.ones((H, W, 1), dtype=np.float32),
    }


def write_plain(path, image, names=("R", "G", "B")):
    """A plain EXR as other tools write it: top-level channels, no layer prefix."""
    channels = {n: np.ascontiguousarray(image[:, :, i]) for i, n in enumerate(names)}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(str(path))


def oidn_files(folder, b, name="shot", colour=".hdr.exr", split=False, depth=False):
    write_plain(folder / f"{name}{colour}", b["diffuse"] + b["specular"])
    write_plain(folder / f"{name}.alb.exr", b["albedo"])
    write_plain(folder / f"{name}.nrm.exr", b["normal"], ("X", "Y", "Z"))
    if split:
        write_plain(folder / f"{name}.diffuse.exr", b["diffuse"])
        write_plain(folder / f"{name}.specular.exr", b["specular"])
    if depth:
        write_plain(folder / f"{name}.depth.exr", b["depth"], ("Z",))
    return folder / f"{name}{colour}"


def test_multilayer_exr_round_trips_through_the_denoiser(tmp_path, denoiser):
    b = buffers()
    b["diffuse"][3, 5, 0] = np.nan
    source = tmp_path / "render.exr"
    write_exr(source, b, precision="float")
    loaded = load_denoise_input(source)
    assert set(loaded.layers) == set(b) and loaded.sources["specular"] == source and loaded.notes == []
    for name in b:
        np.testing.assert_array_equal(loaded.layers[name], b[name])
    assert loaded.nonfinite == {"diffuse": {"nan": 1, "posinf": 0, "neginf": 0, "negative": 0}}

    result = denoiser(loaded.layers)
    assert result.branches == ("diffuse", "specular") and result.sanitized == {"diffuse": {"nan": 1}}
    out = tmp_path / "out" / "render.denoised.exr"
    write_denoised(out, result, source=loaded)
    back = OpenEXR.File(str(out), separate_channels=True).channels()
    assert set(back) == {"R", "G", "B", "diffuse.R", "diffuse.G", "diffuse.B", "specular.R", "specular.G", "specular.B"}
    image = np.stack([back[c].pixels for c in "RGB"], axis=-1)
    assert image.shape == (H, W, 3) and image.dtype == np.float32
    np.testing.assert_array_equal(image, result.image)
    np.testing.assert_array_equal(read_exr(out, ["specular"])["specular"], result.specular)
    assert np.isfinite(image).all() and [p.name for p in out.parent.iterdir()] == ["render.denoised.exr"]


def test_multilayer_without_specular_or_depth_is_diffuse_only_with_constant_depth(tmp_path, denoiser):
    b = buffers()
    source = tmp_path / "plain.exr"
    write_exr(source, {k: b[k] for k in ("diffuse", "albedo", "normal")})
    loaded = load_denoise_input(source)
    assert "depth" not in loaded.layers and "coverage" not in loaded.layers  # the denoiser fills them
    assert any("no specular" in n for n in loaded.notes)
    assert any("constant depth feature 1.0" in n and "coverage 1" in n for n in loaded.notes)
    result = denoiser(loaded.layers)
    assert result.branches == ("diffuse",)
    ones = np.ones((H, W, 1), np.float32)
    np.testing.assert_array_equal(result.image, denoiser(dict(loaded.layers, depth=ones, coverage=ones)).image)
    out = tmp_path / "plain.out.exr"
    write_denoised(out, result, source=loaded)
    channels = set(OpenEXR.File(str(out), separate_channels=True).channels())
    assert channels == {"R", "G", "B", "diffuse.R", "diffuse.G", "diffuse.B"}
    write_denoised(out, result, source=loaded, layers=False)
    assert set(OpenEXR.File(str(out), separate_channels=True).channels()) == {"R", "G", "B"}


@pytest.mark.parametrize("given", ["shot.hdr.exr", "shot"])
def test_oidn_files_with_one_colour_are_diffuse_only(tmp_path, denoiser, given):
    b = buffers(1)
    oidn_files(tmp_path, b)
    loaded = load_denoise_input(tmp_path / given)
    assert set(loaded.layers) == {"diffuse", "albedo", "normal"}  # depth and coverage: the denoiser fills them
    np.testing.assert_array_equal(loaded.layers["diffuse"], b["diffuse"] + b["specular"])
    np.testing.assert_array_equal(loaded.layers["normal"], b["normal"])
    assert loaded.sources["albedo"] == tmp_path / "shot.alb.exr"
    assert any("denoised as diffuse only" in n for n in loaded.notes)
    result = denoiser(loaded.layers)
    assert result.branches == ("diffuse",) and result.image.shape == (H, W, 3)


def test_oidn_files_with_a_split_and_depth_run_both_branches(tmp_path, denoiser):
    b = buffers(2)
    oidn_files(tmp_path, b, colour=".exr", split=True, depth=True)
    loaded = load_denoise_input(tmp_path / "shot.exr")
    for name in ("diffuse", "specular", "albedo", "depth"):
        np.testing.assert_array_equal(loaded.layers[name], b[name])
    assert loaded.notes[0] == "shot.exr: not read, the diffuse/specular split is used"
    assert loaded.notes[1].startswith("shot.nrm.exr: normals (R, G, B) taken as camera space: 100% of the")
    result = denoiser(loaded.layers)
    assert result.branches == ("diffuse", "specular")
    out = tmp_path / "shot.denoised.exr"
    write_denoised(out, result, source=loaded)
    back = read_exr(out, ["diffuse", "specular"])
    assert back["diffuse"].shape == back["specular"].shape == (H, W, 3)
    np.testing.assert_allclose(back["diffuse"] + back["specular"], result.image, rtol=1e-6)


def test_missing_albedo_or_normal_file_is_named(tmp_path):
    oidn_files(tmp_path, buffers())
    (tmp_path / "shot.nrm.exr").unlink()
    with pytest.raises(DenoiseInputError, match=r"shot\.nrm\.exr: missing"):
        load_denoise_input(tmp_path / "shot.hdr.exr")
    (tmp_path / "shot.alb.exr").unlink()
    with pytest.raises(DenoiseInputError, match=r"shot\.alb\.exr: missing"):
        load_denoise_input(tmp_path / "shot.hdr.exr")


def test_missing_layer_in_a_multilayer_exr_is_named(tmp_path):
    b = buffers()
    write_exr(tmp_path / "r.exr", {k: b[k] for k in ("diffuse", "albedo")})
    with pytest.raises(DenoiseInputError, match=r"r\.exr: lacks layer\(s\) normal"):
        load_denoise_input(tmp_path / "r.exr")


def test_files_of_different_sizes_are_refused(tmp_path):
    b = buffers()
    oidn_files(tmp_path, b)
    write_plain(tmp_path / "shot.alb.exr", b["albedo"][:, :20])
    with pytest.raises(DenoiseInputError, match=r"differ in size .*shot\.alb\.exr 24x20"):
        load_denoise_input(tmp_path / "shot")


def test_half_a_split_is_refused(tmp_path):
    b = buffers()
    oidn_files(tmp_path, b, split=True)
    (tmp_path / "shot.specular.exr").unlink()
    with pytest.raises(DenoiseInputError, match=r"shot\.diffuse\.exr: found without .*shot\.specular\.exr"):
        load_denoise_input(tmp_path / "shot.hdr.exr")


def test_not_an_exr_and_truncated_files_are_named(tmp_path):
    b = buffers()
    oidn_files(tmp_path, b)
    (tmp_path / "shot.alb.exr").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    with pytest.raises(ExrError, match=r"shot\.alb\.exr: not an OpenEXR file \(it is a PNG image\)"):
        load_denoise_input(tmp_path / "shot.hdr.exr")
    write_exr(tmp_path / "cut.exr", b)
    data = (tmp_path / "cut.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 3])
    with pytest.raises(ExrError, match=r"cut\.exr"):
        load_denoise_input(tmp_path / "cut.exr")


def test_nothing_to_read_is_named(tmp_path):
    with pytest.raises(DenoiseInputError, match=r"nothing: no such file.*nothing\.hdr\.exr"):
        load_denoise_input(tmp_path / "nothing")


def test_plain_rgb_exr_without_feature_files_is_refused(tmp_path):
    write_plain(tmp_path / "beauty.exr", buffers()["diffuse"])
    with pytest.raises(DenoiseInputError, match=r"beauty\.exr: read as EXR, lacks albedo, normal needed .*--layers"):
        load_denoise_input(tmp_path / "beauty.exr")


def test_writing_over_an_input_file_is_refused(tmp_path, denoiser):
    b = buffers()
    source = oidn_files(tmp_path, b)
    loaded = load_denoise_input(source)
    result = denoiser(loaded.layers)
    before = (tmp_path / "shot.alb.exr").read_bytes()
    for target in ("shot.hdr.exr", "shot.alb.exr"):
        with pytest.raises(DenoiseInputError, match="is one of the input files"):
            write_denoised(tmp_path / target, result, source=loaded)
    assert (tmp_path / "shot.alb.exr").read_bytes() == before
    with pytest.raises(DenoiseInputError, match="must be an .exr"):
        write_denoised(tmp_path / "out.png", result, source=loaded)
