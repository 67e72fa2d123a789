"""EXR store: real files written and read back with OpenEXR and OpenImageIO."""

import numpy as np
import OpenEXR
import OpenImageIO as oiio
import pytest

from admc.common.buffers import BEAUTY, LAYERS
from admc.stores.exr import ExrError, exr_layers, nonfinite_report, read_exr, read_image, write_exr


def make_layers(h=16, w=24, seed=0, names=tuple(LAYERS)):
    rng = np.random.default_rng(seed)
    return {name: (rng.standard_normal((h, w, len(LAYERS[name].channels))) * 50).astype(np.float32) for name in names}


def write_oiio(path, pixels, fmt="float"):
    out = oiio.ImageOutput.create(str(path))
    h, w, c = pixels.shape
    assert out.open(str(path), oiio.ImageSpec(w, h, c, fmt))
    assert out.write_image(pixels)
    out.close()


def test_half_round_trip_equals_float16_cast(tmp_path):
    layers = make_layers()
    write_exr(tmp_path / "a.exr", layers, precision="half")
    back = read_exr(tmp_path / "a.exr")
    assert sorted(back) == sorted(LAYERS)
    for name, array in layers.items():
        assert back[name].dtype == np.float32 and back[name].shape == array.shape
        np.testing.assert_array_equal(back[name], array.astype(np.float16).astype(np.float32))
    assert not np.array_equal(back["diffuse"], layers["diffuse"])  # half really lost precision


def test_float_round_trip_is_exact_and_keeps_attributes(tmp_path):
    layers = make_layers(names=("diffuse", "albedo", "normal", "depth"))
    layers["diffuse"][0, 0] = 1e9  # fine in float
    write_exr(
        tmp_path / "ref.exr", layers, precision="float", attributes={"admc_scene": "room-0003", "admc_spp": "4096"}
    )
    back = read_exr(tmp_path / "ref.exr", ["depth", "diffuse"])
    assert list(back) == ["depth", "diffuse"]
    np.testing.assert_array_equal(back["diffuse"], layers["diffuse"])
    np.testing.assert_array_equal(back["depth"], layers["depth"])
    header = OpenEXR.File(str(tmp_path / "ref.exr"), header_only=True).header()
    assert header["admc_scene"] == "room-0003" and header["admc_spp"] == "4096"
    channel_types = {
        c.name: c.type() for c in OpenEXR.File(str(tmp_path / "ref.exr"), separate_channels=True).channels().values()
    }
    assert channel_types["diffuse.R"] == OpenEXR.FLOAT and channel_types["depth.Z"] == OpenEXR.FLOAT
    assert exr_layers(tmp_path / "ref.exr") == ["albedo", "depth", "diffuse", "normal"]


def test_write_is_atomic_and_leaves_no_temp_files(tmp_path):
    write_exr(tmp_path / "out" / "a.exr", make_layers(names=("depth",)))
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["a.exr"]
    with pytest.raises(ExrError, match="65504"):
        write_exr(tmp_path / "out" / "a.exr", {"depth": np.full((4, 4, 1), 7e4, np.float32)})
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["a.exr"]  # the old file survives untouched
    assert read_exr(tmp_path / "out" / "a.exr")["depth"].shape == (16, 24, 1)


def test_half_refuses_overflow_but_keeps_existing_inf_and_nan(tmp_path):
    depth = np.ones((4, 4, 1), np.float32)
    depth[0, 0], depth[0, 1], depth[0, 2] = np.inf, np.nan, 65504.0
    write_exr(tmp_path / "a.exr", {"depth": depth})
    back = read_exr(tmp_path / "a.exr")["depth"]
    assert np.isposinf(back[0, 0, 0]) and np.isnan(back[0, 1, 0]) and back[0, 2, 0] == 65504.0
    depth[1, 1] = -1e5
    with pytest.raises(ExrError, match=r"a\.exr.*'depth' has 1 finite values"):
        write_exr(tmp_path / "a.exr", {"depth": depth})
    write_exr(tmp_path / "b.exr", {"depth": depth}, precision="float")
    assert read_exr(tmp_path / "b.exr")["depth"][1, 1, 0] == -1e5


@pytest.mark.parametrize(
    "layers, message",
    [
        ({"beauty": np.zeros((4, 4, 3), np.float32)}, "unknown layer 'beauty'"),
        ({"normal": np.zeros((4, 4, 1), np.float32)}, r"'normal' must be \(H, W, 3\)"),
        ({"depth": np.zeros((4, 4), np.float32)}, r"'depth' must be \(H, W, 1\)"),
        ({"depth": np.zeros((4, 4, 1), np.float32), "albedo": np.zeros((4, 5, 3), np.float32)}, "differ in size"),
        ({"depth": np.zeros((4, 4, 1), np.int32)}, "must be a float array"),
        ({}, "no layers"),
    ],
)
def test_write_rejects_bad_layers(tmp_path, layers, message):
    with pytest.raises(ExrError, match=message):
        write_exr(tmp_path / "bad.exr", layers)
    assert not list(tmp_path.iterdir())


def test_write_rejects_bad_precision_and_attributes(tmp_path):
    layers = make_layers(names=("depth",))
    with pytest.raises(ExrError, match="precision"):
        write_exr(tmp_path / "a.exr", layers, precision="double")
    with pytest.raises(ExrError, match="'compression'"):
        write_exr(tmp_path / "a.exr", layers, attributes={"compression": "none"})
    with pytest.raises(ExrError, match="'spp'"):
        write_exr(tmp_path / "a.exr", layers, attributes={"spp": 4})


def test_missing_file(tmp_path):
    with pytest.raises(ExrError, match=r"nope\.exr: no such file"):
        read_exr(tmp_path / "nope.exr")
    with pytest.raises(ExrError, match="no such file"):
        exr_layers(tmp_path / "nope.exr")


def test_garbage_bytes_are_not_an_exr(tmp_path):
    (tmp_path / "junk.exr").write_bytes(b"this is not an image at all" * 40)
    with pytest.raises(ExrError, match=r"junk\.exr: not an OpenEXR file \(starts with b'this'\)"):
        read_exr(tmp_path / "junk.exr")


def test_renamed_png_is_named_as_png(tmp_path):
    write_oiio(tmp_path / "pic.png", np.full((8, 8, 3), 0.5, np.float32), fmt="uint8")
    (tmp_path / "pic.png").rename(tmp_path / "pic.exr")
    with pytest.raises(ExrError, match=r"pic\.exr: not an OpenEXR file \(it is a PNG image\)"):
        read_exr(tmp_path / "pic.exr")
    with pytest.raises(ExrError, match="PNG"):
        exr_layers(tmp_path / "pic.exr")


def test_truncated_file(tmp_path):
    write_exr(tmp_path / "full.exr", make_layers(64, 64), precision="float")
    data = (tmp_path / "full.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(ExrError, match=r"cut\.exr: truncated or corrupt"):
        read_exr(tmp_path / "cut.exr")


def test_missing_layer_names_what_exists(tmp_path):
    write_exr(tmp_path / "a.exr", make_layers(names=("diffuse", "albedo")))
    with pytest.raises(ExrError, match=r"a\.exr: has no layer 'specular'; it holds albedo, diffuse"):
        read_exr(tmp_path / "a.exr", ["diffuse", "specular"])
    with pytest.raises(ExrError, match="unknown layer 'beauty'"):
        read_exr(tmp_path / "a.exr", ["beauty"])


def test_layer_with_only_some_channels(tmp_path):
    plane = np.ones((4, 4), np.float32)
    OpenEXR.File({}, {"normal.X": plane.copy(), "normal.Z": plane.copy(), "depth.Z": plane.copy()}).write(
        str(tmp_path / "partial.exr")
    )
    with pytest.raises(ExrError, match=r"partial\.exr: layer 'normal' lacks channel\(s\) Y \(has X, Z\)"):
        read_exr(tmp_path / "partial.exr")
    assert read_exr(tmp_path / "partial.exr", ["depth"])["depth"].shape == (4, 4, 1)


def test_subsampled_channel_is_an_inconsistent_size(tmp_path):
    full = np.ones((8, 8), np.float32)
    channels = {
        "albedo.R": OpenEXR.Channel("albedo.R", full.copy()),
        "albedo.G": OpenEXR.Channel("albedo.G", full.copy()),
        "albedo.B": OpenEXR.Channel("albedo.B", full.copy(), 2, 2),
    }  # stored 4x4
    OpenEXR.File({}, channels).write(str(tmp_path / "sub.exr"))
    with pytest.raises(ExrError, match=r"sub\.exr: channel albedo\.B is 4x4, the image is 8x8"):
        read_exr(tmp_path / "sub.exr")


def test_plain_rgb_file_is_the_beauty_layer_only(tmp_path):
    write_oiio(tmp_path / "rgb.exr", np.full((4, 4, 3), 0.5, np.float32))
    assert exr_layers(tmp_path / "rgb.exr") == [BEAUTY]
    np.testing.assert_array_equal(read_exr(tmp_path / "rgb.exr")[BEAUTY], np.full((4, 4, 3), 0.5, np.float32))
    with pytest.raises(ExrError, match=r"rgb\.exr: has no layer 'diffuse'"):
        read_exr(tmp_path / "rgb.exr", ["diffuse"])


def test_beauty_round_trips_as_plain_rgb_channels(tmp_path):
    image = np.random.default_rng(0).random((5, 6, 3), dtype=np.float32)
    write_exr(tmp_path / "out.exr", {BEAUTY: image, "diffuse": image * 0.5}, precision="float")
    assert sorted(OpenEXR.File(str(tmp_path / "out.exr")).header()["channels"][i].name for i in range(6)) == [
        "B",
        "G",
        "R",
        "diffuse.B",
        "diffuse.G",
        "diffuse.R",
    ]
    np.testing.assert_array_equal(read_exr(tmp_path / "out.exr")[BEAUTY], image)


def test_openimageio_reads_what_write_exr_wrote(tmp_path):
    layers = make_layers(names=("diffuse", "depth"))
    write_exr(tmp_path / "a.exr", layers, precision="float")
    pixels = read_image(tmp_path / "a.exr")
    spec = oiio.ImageInput.open(str(tmp_path / "a.exr")).spec()
    order = list(spec.channelnames)
    assert sorted(order) == ["depth.Z", "diffuse.B", "diffuse.G", "diffuse.R"]
    assert pixels.shape == (16, 24, 4) and pixels.dtype == np.float32
    np.testing.assert_array_equal(pixels[..., order.index("diffuse.G")], layers["diffuse"][..., 1])
    np.testing.assert_array_equal(pixels[..., order.index("depth.Z")], layers["depth"][..., 0])


def test_read_image_pfm_hdr_png_top_row_first(tmp_path):
    ramp = np.linspace(0.0, 4.0, 6 * 7 * 3, dtype=np.float32).reshape(6, 7, 3)
    write_oiio(tmp_path / "a.pfm", ramp)
    np.testing.assert_array_equal(read_image(tmp_path / "a.pfm"), ramp)
    # A PFM written by hand by the spec: rows stored bottom row first.
    (tmp_path / "b.pfm").write_bytes(b"PF\n7 6\n-1.0\n" + ramp[::-1].astype("<f4").tobytes())
    np.testing.assert_array_equal(read_image(tmp_path / "b.pfm"), ramp)
    write_oiio(tmp_path / "a.hdr", ramp)
    error = np.abs(read_image(tmp_path / "a.hdr") - ramp)
    assert np.all(error <= ramp.max(axis=-1, keepdims=True) / 128)  # RGBE: 8-bit mantissas, one shared exponent
    write_oiio(tmp_path / "a.png", ramp / 4, fmt="uint8")
    np.testing.assert_allclose(read_image(tmp_path / "a.png"), ramp / 4, atol=0.5 / 255 + 1e-6)


def test_read_image_errors(tmp_path):
    with pytest.raises(ExrError, match=r"x\.hdr: no such file"):
        read_image(tmp_path / "x.hdr")
    (tmp_path / "x.png").write_bytes(b"garbage")
    with pytest.raises(ExrError, match=r"x\.png: OpenImageIO cannot open it"):
        read_image(tmp_path / "x.png")


def test_nonfinite_report_counts_per_layer():
    diffuse = np.zeros((4, 4, 3), np.float32)
    diffuse[0, 0, 0], diffuse[0, 1, 1], diffuse[1, 1, 2], diffuse[2, 2, 0] = np.nan, np.inf, -np.inf, -0.5
    normal = -np.ones((4, 4, 3), np.float32)
    normal[3, 3, 0] = np.nan
    report = nonfinite_report({"diffuse": diffuse, "normal": normal, "albedo": np.ones((4, 4, 3), np.float32)})
    assert report == {
        "diffuse": {"nan": 1, "posinf": 1, "neginf": 1, "negative": 1},
        "normal": {"nan": 1, "posinf": 0, "neginf": 0, "negative": 0},
    }
    assert nonfinite_report({"normal": normal}, negative_layers={"normal"})["normal"]["negative"] == 47
