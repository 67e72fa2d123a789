"""The CPU engines behind FullImageDenoiser: ONNX Runtime and OpenVINO give torch's result, tiled, with the
ensemble and the dark pass around them; what an engine cannot do is refused."""

import numpy as np
import pytest
import torch
from test_export import FLOAT32_LOG_TOLERANCE
from test_inference import render_layers

from admc.model.inference.denoiser import load_denoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.engines import OPENVINO_SIZES, OPENVINO_STREAMS, OnnxGenerator, run_together
from admc.model.precision import cpu_has_fast_bf16
from admc.model.transforms import diffuse_forward, specular_forward
from admc.pipeline.weights import WEIGHTS_DIR

SHIPPED = WEIGHTS_DIR / "admc-small-pretrained.pt"
BF16_ERROR_RATIO = 2.0
"""bf16 keeps 8 significant bits (unit roundoff 2^-8) of each conv's inputs and weights in either engine;
how far a bf16 run lies from float32 depends on where the engine rounds, not on which engine it is, so
OpenVINO's mean log error may be at most this many times torch autocast's own on the same image."""


def log_branches(result, layers):
    """The result's branches in the networks' log domain, where a rounding error is a relative one."""
    return np.concatenate([diffuse_forward(result.diffuse, layers["albedo"]), specular_forward(result.specular)])


def dark_layers():
    """A bright image with a shadowed corner, so that the dark pass runs on part of it."""
    layers = render_layers(56, 72, seed=3)
    for name in ("diffuse", "specular"):
        layers[name][30:, 40:] *= 1e-3
    return layers


@pytest.mark.parametrize("engine", ["onnxruntime", "openvino"])
@pytest.mark.parametrize("tile", [None, 20])
def test_float32_engines_give_the_torch_result(engine, tile):
    layers = dark_layers()
    options = dict(tile=tile, dtype=torch.float32, dark_pass=True, ensemble=2)
    reference = load_denoiser(SHIPPED, DenoiserOptions(**options))(layers)
    denoiser = load_denoiser(SHIPPED, DenoiserOptions(engine=engine, **options))
    assert isinstance(denoiser.generators["diffuse"], OnnxGenerator)
    assert f"{engine} float32" in denoiser.device  # said next to its timings in the tables
    result = denoiser(layers)
    assert result.dark_share > 0 and result.tiles == reference.tiles
    error = np.abs(log_branches(result, layers) - log_branches(reference, layers))
    assert error.max() <= FLOAT32_LOG_TOLERANCE


def test_openvino_in_the_precision_it_picks_gives_the_torch_result():
    """bf16 where the CPU computes it (AVX512-BF16 or AMX), float32 elsewhere; tiled."""
    layers = render_layers(48, 64, seed=4)
    exact = log_branches(load_denoiser(SHIPPED, DenoiserOptions(tile=20, dtype=torch.float32))(layers), layers)
    denoiser = load_denoiser(SHIPPED, DenoiserOptions(tile=20, engine="openvino"))
    error = np.abs(log_branches(denoiser(layers), layers) - exact)
    if not cpu_has_fast_bf16():
        assert denoiser.dtype == torch.float32 and error.max() <= FLOAT32_LOG_TOLERANCE
        return
    assert denoiser.dtype == torch.bfloat16
    torch_bf16 = np.abs(
        log_branches(load_denoiser(SHIPPED, DenoiserOptions(tile=20, dtype=torch.bfloat16))(layers), layers) - exact
    )
    assert error.mean() <= BF16_ERROR_RATIO * torch_bf16.mean(), (error.mean(), torch_bf16.mean())


@pytest.mark.parametrize(
    "engine,options,message",
    [
        ("tensorrt", {}, "engine 'tensorrt': not one of auto, torch, onnxruntime, openvino"),
        ("onnxruntime", {"dtype": torch.bfloat16}, "engine 'onnxruntime' runs float32 only"),
        ("openvino", {"compile": True}, "compile is torch.compile"),
    ],
)
def test_what_an_engine_cannot_do_is_refused(engine, options, message):
    with pytest.raises(ValueError, match=message):
        load_denoiser(SHIPPED, DenoiserOptions(engine=engine, **options))


def test_auto_is_openvino_on_a_cpu():
    denoiser = load_denoiser(SHIPPED, DenoiserOptions(engine="auto"))
    assert denoiser.engine == "openvino" and isinstance(denoiser.generators["specular"], OnnxGenerator)


@pytest.mark.parametrize("engine", ["onnxruntime", "openvino"])
@pytest.mark.parametrize("shipped", ["admc-small-pretrained.pt", "admc-small-refiner.pt"])
def test_float32_engines_give_the_torch_result_for_noise_input_weights(engine, shipped, tmp_path):
    """model.noise_input weights: the graph takes the noise map as an input of its own; tiled, with the
    ensemble and the dark pass, each engine gives torch's result within the same float32 tolerance."""
    from conftest import noise_input_weights
    from test_inference import with_variance

    weights = noise_input_weights(tmp_path / "noise.pt", shipped)
    layers = with_variance(dark_layers())
    options = dict(tile=20, dtype=torch.float32, dark_pass=True, ensemble=2)
    reference = load_denoiser(weights, DenoiserOptions(**options))(layers)
    denoiser = load_denoiser(weights, DenoiserOptions(engine=engine, **options))
    assert all(g.noise_input for g in denoiser.generators.values())
    result = denoiser(layers)
    assert result.dark_share > 0 and result.tiles == reference.tiles
    error = np.abs(log_branches(result, layers) - log_branches(reference, layers))
    assert error.max() <= FLOAT32_LOG_TOLERANCE
    # the map reaches the graph where torch reads it: other variances move torch's output beyond twice the
    # tolerance's worst case, and the engine's with it, to within the tolerance
    quieter = {**layers, "diffuse_var": layers["diffuse_var"] * 1e-6}
    moved = log_branches(load_denoiser(weights, DenoiserOptions(**options))(quieter), layers)
    assert np.abs(moved - log_branches(reference, layers)).max() > 2 * FLOAT32_LOG_TOLERANCE
    assert np.abs(log_branches(denoiser(quieter), layers) - moved).max() <= FLOAT32_LOG_TOLERANCE


def test_openvino_compiles_for_each_size_it_sees_and_keeps_the_last_few():
    """Each size gets a graph compiled for it (faster than the graph of any size) with torch's result; the
    oldest beyond OPENVINO_SIZES is let go, and a size seen again is reused."""
    exact = load_denoiser(SHIPPED, DenoiserOptions(dtype=torch.float32)).generators["diffuse"]
    generator = load_denoiser(SHIPPED, DenoiserOptions(engine="openvino", dtype=torch.float32)).generators["diffuse"]
    sizes = [(8 + i, 12 + 2 * i) for i in range(OPENVINO_SIZES + 1)]
    generator_rng = torch.Generator().manual_seed(5)
    for height, width in sizes + sizes[-1:]:
        noisy = torch.rand((1, 3, height, width), generator=generator_rng) * 4
        features = torch.rand((1, 7, height, width), generator=generator_rng)
        with torch.inference_mode():
            reference = exact(noisy, features)
        assert (generator(noisy, features) - reference).abs().max() <= FLOAT32_LOG_TOLERANCE
        assert (generator.one_off(noisy, features) - reference).abs().max() <= FLOAT32_LOG_TOLERANCE
    assert generator.compiled_sizes == sizes[1:]


def test_the_dark_pass_compiles_nothing_for_its_crop():
    """The dark pass's crop is a size of its own per image: it runs in the graph of any size."""
    layers = dark_layers()
    denoiser = load_denoiser(SHIPPED, DenoiserOptions(engine="openvino", dark_pass=True))
    assert denoiser(layers).dark_share > 0
    assert all(g.compiled_sizes == [layers["diffuse"].shape[:2]] for g in denoiser.generators.values())


def openvino_with_threads(threads: int, **options):
    """The shipped weights in OpenVINO float32, built while torch has `threads` threads (the engine's own
    thread count is fixed then; the suite runs torch at one)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return load_denoiser(SHIPPED, DenoiserOptions(engine="openvino", dtype=torch.float32, **options))
    finally:
        torch.set_num_threads(previous)


@pytest.mark.parametrize("height,width,tile,tiles", [(48, 64, 20, 12), (40, 56, None, 1)])
def test_openvino_runs_calls_together_with_the_torch_result(height, width, tile, tiles):
    """With two threads an image's tiles, and both branches of an image of one tile, run OPENVINO_STREAMS at
    a time, each on one thread: torch's result, and calls of one size share one compiled graph."""
    layers = render_layers(height, width, seed=6)
    exact = log_branches(load_denoiser(SHIPPED, DenoiserOptions(tile=tile, dtype=torch.float32))(layers), layers)
    denoiser = openvino_with_threads(2, tile=tile)
    result = denoiser(layers)
    assert result.tiles == tiles
    assert np.abs(log_branches(result, layers) - exact).max() <= FLOAT32_LOG_TOLERANCE
    assert all([streams for *_, streams in g._sized] == [OPENVINO_STREAMS] for g in denoiser.generators.values())


def test_openvino_calls_stopped_early_wait_for_their_requests():
    """A caller that stops taking run_together's outputs (an error while it writes a tile) leaves no request
    running on inputs that are then freed; the next calls give the right outputs. The first call is tiny
    and the second large (tens of ms), so the second is still running when the first comes back."""
    exact = load_denoiser(SHIPPED, DenoiserOptions(dtype=torch.float32)).generators["diffuse"]
    generator = openvino_with_threads(2).generators["diffuse"]
    rng = torch.Generator().manual_seed(7)
    sizes = [(8, 12), (192, 256), (8, 12)]
    calls = [
        (generator, (torch.rand((1, 3, *size), generator=rng) * 4, torch.rand((1, 7, *size), generator=rng)))
        for size in sizes
    ]
    with torch.inference_mode():
        references = [exact(*inputs) for _, inputs in calls]
    outputs = run_together(calls)
    first = next(outputs)
    outputs.close()
    assert generator._sized[(192, 256, OPENVINO_STREAMS)][1].wait_for(0)  # the second call's request is done
    assert (first - references[0]).abs().max() <= FLOAT32_LOG_TOLERANCE
    for output, reference in zip(run_together(calls), references, strict=True):
        assert (output - reference).abs().max() <= FLOAT32_LOG_TOLERANCE
