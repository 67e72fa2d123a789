"""OIDN's U-Net in torch (model/nets/oidn_unet.py) against the OIDN library itself, and its weight archives.

The torch network must be OIDN to start from: on real renders its output is the library's up to arithmetic.
The library computes in float32, except on CPUs with AMX-FP16, where it runs its convolutions in float16;
the tolerance follows the precision the library uses on this machine.
"""

import numpy as np
import pytest
import torch

from admc.common import oidn
from admc.model.inference.fine_tuned_oidn import partner_archives, partner_bases
from admc.model.nets.oidn_unet import OidnUNet, OidnUNetLarge, autoexposure, batch_exposure, clean_guides, oidn_unet
from admc.model.inference.oidn_base import oidn_bases
from admc.stores.oidn_archives import ArchiveError, library_archives, read_archive, write_archive


def _library_fp16() -> bool:
    try:
        return "amx_fp16" in open("/proc/cpuinfo").read()
    except OSError:
        return False


# float32: 16 conv layers of sums over at most 1000 terms differ by ordering, ~1e-6 relative (measured
# 1.2e-6 here), with 100x margin; float16 activations: ~1e-3 per layer, amplified by the PU inverse.
TOLERANCE = 3e-2 if _library_fp16() else 1e-4


@pytest.fixture(scope="module")
def render(variant):
    """A real 40x56 Cornell box at 4 spp: diffuse, specular, albedo and normal (sanitised as admc passes them)."""
    import mitsuba as mi

    from admc.common.buffers import sanitize

    scene = mi.cornell_box()
    scene["sensor"]["film"] = {"type": "hdrfilm", "width": 56, "height": 40, "rfilter": {"type": "box"}}
    scene["integrator"] = {"type": "aov", "aovs": "albedo:albedo,normal:sh_normal", "beauty": {"type": "path"}}
    image = np.array(mi.render(mi.load_dict(scene), spp=4))
    color = sanitize(image[..., :3], "diffuse")[0]
    albedo = sanitize(image[..., 3:6], "albedo")[0]
    normal = sanitize(image[..., 6:9], "normal")[0]
    return {"diffuse": color, "specular": np.ascontiguousarray(color * 0.3), "albedo": albedo, "normal": normal}


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).mean() / np.abs(b).mean())


@pytest.mark.parametrize("branch", ["diffuse", "specular"])
def test_the_torch_network_is_the_librarys_on_a_render(render, branch):
    """Same weights, same input path (autoexposure, PU transfer, zero padding to 16 of a 40x56 image)."""
    net = oidn_unet(branch)
    tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]  # noqa: E731
    guides = (tensor(render["albedo"]), tensor(render["normal"])) if branch == "diffuse" else ()
    with torch.no_grad():
        ours = net.denoise(tensor(render[branch]), autoexposure(render[branch]), *guides)[0].numpy().transpose(1, 2, 0)
    theirs = oidn.denoise(render[branch], *((render["albedo"], render["normal"]) if guides else ()), quality="high")
    assert _relative(ours, theirs) < TOLERANCE
    # and it denoises: far from its noisy input
    assert _relative(ours, render[branch]) > 10 * TOLERANCE


def test_the_partner_runs_in_oidn_and_from_oidns_weights_gives_oidns_bases(render):
    """A fine-tune's partner before any step, written as TZA archives and run by the OIDN library, is OIDN's
    per-branch output (the archives hold the library's float16 weights exactly); the ensemble of four
    symmetries (normals following the geometry) stays near it; other weights give another image."""
    nets = {b: oidn_unet(b) for b in ("diffuse", "specular")}
    archives = partner_archives({b: net.state_dict() for b, net in nets.items()}, "test")
    library = oidn_bases(render, "oidn")
    for ensemble, tolerance in ((1, 1e-6), (4, 0.1)):
        ours = partner_bases(archives, render, ("diffuse", "specular"), ensemble)
        for branch in ("diffuse", "specular"):
            assert ours[branch].dtype == np.float32 and (ours[branch] >= 0).all()
            assert _relative(ours[branch], library[branch]) < tolerance
    state = nets["diffuse"].state_dict()
    state["dec_conv0.bias"] = state["dec_conv0.bias"] + 0.05
    other = partner_bases(partner_archives({"diffuse": state}, "test"), render, ("diffuse",))
    assert _relative(other["diffuse"], library["diffuse"]) > 0.01


def test_the_large_network_on_prefiltered_guides_is_oidns_final_frame_route(render):
    """train.oidn_network = "large": OIDN's large clean-guide network in torch, on guides OIDN's own networks
    prefiltered, is the library's final-frame route (prefilter, then cleanAux); as a partner archive the library
    runs it with the same prefilter. It is not the standard route's image."""
    tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]  # noqa: E731
    albedo, normal = oidn.prefilter("albedo", render["albedo"]), oidn.prefilter("normal", render["normal"])
    theirs = oidn.denoise(render["diffuse"], albedo, normal, quality="high", clean_aux=True)
    guides = clean_guides(tensor(render["albedo"]), tensor(render["normal"]))
    assert np.array_equal(guides[0][0].numpy().transpose(1, 2, 0), albedo)
    net = oidn_unet("diffuse", "large")
    assert isinstance(net, OidnUNetLarge) and sum(p.numel() for p in net.parameters()) == 3_848_387
    with torch.no_grad():
        ours = net.denoise(tensor(render["diffuse"]), autoexposure(render["diffuse"]), *guides)
    assert _relative(ours[0].numpy().transpose(1, 2, 0), theirs) < TOLERANCE
    archives = partner_archives(
        {"diffuse": net.state_dict(), "specular": oidn_unet("specular", "large").state_dict()}, "t"
    )
    bases = partner_bases(archives, render, ("diffuse", "specular"))
    assert _relative(bases["diffuse"], theirs) < 1e-6
    standard = oidn_bases(render, "oidn")
    assert _relative(bases["diffuse"], standard["diffuse"]) > 0.01  # a different network on other guides
    assert _relative(bases["specular"], standard["specular"]) < 1e-6  # OIDN has no large colour-only network


def test_an_archive_written_reads_back_as_it_was():
    tensors = {"enc_conv0.weight": np.arange(54, dtype=np.float32).reshape(2, 3, 3, 3) / 7, "b": np.ones(5)}
    back = read_archive(write_archive(tensors))
    assert list(back) == list(tensors)
    for name, tensor in tensors.items():
        assert np.array_equal(back[name], tensor.astype(np.float16).astype(np.float32))


def test_batch_exposure_is_oidns_autoexposure_on_patches():
    rng = np.random.default_rng(0)
    patches = rng.exponential(1.0, (3, 64, 48, 3)).astype(np.float32) * np.array([1e-3, 1.0, 50.0])[:, None, None, None]
    patches[2, :16] = 0.0  # dark bins are left out
    ours = batch_exposure(torch.from_numpy(patches.transpose(0, 3, 1, 2).copy())).flatten()
    expected = [autoexposure(p) for p in patches]
    assert np.allclose(ours.numpy(), expected, rtol=1e-5)
    assert float(batch_exposure(torch.zeros(1, 3, 32, 32))) == 1.0 == autoexposure(np.zeros((32, 32, 3)))


def test_the_library_carries_both_networks_and_a_damaged_archive_is_refused(tmp_path):
    archives = library_archives()
    shapes = {a["enc_conv0.weight"].shape[1] for a in archives if "enc_conv0.weight" in a}
    assert {3, 9} <= shapes
    net = OidnUNet(9)
    assert sum(p.numel() for p in net.parameters()) == 919_811  # OIDN's default U-Net on colour, albedo, normal
    with pytest.raises(ArchiveError, match=r"mine\.tza: not a readable OIDN weight archive at byte 0"):
        read_archive(b"not an archive", 0, "mine.tza")
    blob = tmp_path / "blob.so"
    blob.write_bytes(b"\xd7\x41\x02\x00" + b"\xff" * 64)
    with pytest.raises(ArchiveError, match=r"blob\.so: no OIDN weight archive found"):
        library_archives(blob)
    with pytest.raises(ArchiveError, match=r"missing\.so: cannot read OIDN's library"):
        library_archives(tmp_path / "missing.so")
