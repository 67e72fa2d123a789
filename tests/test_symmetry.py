"""Test-time self-ensembling: the 8 symmetries on a batch are training's augmentation of each item, and
an 8-way ensemble denoiser is equivariant to them, as a group average must be."""

import numpy as np
import pytest
import torch

from admc.common.layout import ENSEMBLES
from admc.model.inference.denoiser import FullImageDenoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.symmetry import ENSEMBLE_CODES, N_SYMMETRIES, apply, undo
from admc.model.transforms import diffuse_forward, specular_forward
from test_inference import log_tolerance, render_layers, strong_generator


@pytest.mark.parametrize("code", range(N_SYMMETRIES))
def test_batch_symmetries_are_each_items_augmentation_and_undo_inverts_them(code):
    rng = np.random.default_rng(code)
    features = rng.random((2, 7, 5, 9), dtype=np.float32)
    original = features.copy()
    applied = apply(torch.from_numpy(features), code, normals=True)
    np.testing.assert_array_equal(features, original)  # the input is left alone (the normals are edited in copies)
    for n in range(2):
        np.testing.assert_array_equal(
            applied[n].numpy(), apply(torch.from_numpy(features[n]), code, normals=True).numpy()
        )
    image = torch.from_numpy(features[:, :3])
    assert torch.equal(undo(apply(image, code), code), image)


def test_every_ensemble_size_uses_distinct_symmetries_starting_with_the_identity():
    assert tuple(ENSEMBLE_CODES) == ENSEMBLES
    for size, codes in ENSEMBLE_CODES.items():
        assert len(set(codes)) == size and codes[0] == 0


def _transposed(layers: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The render of the transposed image: pixels (r, c) -> (c, r), view-space normal (x, y) -> (-y, -x)."""
    out = {name: np.ascontiguousarray(array.transpose(1, 0, 2)) for name, array in layers.items()}
    x, y = out["normal"][..., 0].copy(), out["normal"][..., 1].copy()
    out["normal"][..., 0], out["normal"][..., 1] = -y, -x
    return out


def test_an_eight_way_ensemble_is_equivariant_and_one_way_is_the_plain_denoiser(inference_dtype):
    diffuse, specular = strong_generator(2, scale=0.7), strong_generator(3, scale=0.7)
    layers = render_layers(24, 40)
    plain_denoiser = FullImageDenoiser(diffuse, specular, DenoiserOptions(dtype=inference_dtype))
    plain = plain_denoiser(layers)
    assert np.array_equal(
        FullImageDenoiser(diffuse, specular, DenoiserOptions(dtype=inference_dtype, ensemble=1))(layers).image,
        plain.image,
    )
    ensemble = FullImageDenoiser(diffuse, specular, DenoiserOptions(dtype=inference_dtype, ensemble=8))
    assert ensemble.device.endswith(", ensemble of 8")  # said next to its timings in the tables
    result = ensemble(layers)
    assert np.abs(plain.image - result.image).max() > 1e-3  # the ensemble is not the plain output
    # Both runs average the same 8 network evaluations in another order, each seeing its input in
    # another memory layout: the same network on the same inputs, summing in another order. Compared
    # in the networks' log domain, where that bound is derived (test_inference.log_tolerance); the
    # plain denoiser, not equivariant, must miss it (the check can fail).
    albedo = layers["albedo"]
    for denoiser, equivariant in ((ensemble, True), (plain_denoiser, False)):
        here, moved = denoiser(layers), denoiser(_transposed(layers))
        for branch, forward in (("diffuse", lambda x: diffuse_forward(x, albedo)), ("specular", specular_forward)):
            expected = forward(getattr(here, branch))
            error = np.abs(forward(getattr(moved, branch).transpose(1, 0, 2)) - expected).max()
            assert (error <= log_tolerance(inference_dtype, np.abs(expected).max())) == equivariant, branch


def test_an_ensemble_size_that_is_not_offered_is_refused():
    with pytest.raises(ValueError, match=r"ensemble must be one of \(1, 2, 4, 8\), got 3"):
        FullImageDenoiser(strong_generator(0), None, DenoiserOptions(ensemble=3))
