"""`admc-pipe export`: the shipped weights' generators as ONNX graphs, run by ONNX Runtime, equal torch's
float32 forward pass at sizes the trace never saw, darkness gate included; and its user errors."""

import json

import numpy as np
import onnxruntime
import pytest
import torch
from test_cli import run
from test_user_errors_cli import refused

from admc.common.layout import BASE_QUALITIES
from admc.model.inference.denoiser import load_denoiser
from admc.model.inference.options import DenoiserOptions
from admc.pipeline.stages.export import export_onnx
from admc.pipeline.weights import WEIGHTS_DIR

FLOAT32_LOG_TOLERANCE = 1e-3
"""ONNX Runtime sums each conv's n products in another order than torch: float32 rounding of at most
n * 2^-24 relative per conv (n <= 144 = 9 x 16 in the small model: 8.6e-6), through its ~17 convs (head,
4 blocks of 2, body, tail 2, encoder 5) on activations of magnitude <= ~10: 17 x 8.6e-6 x 10 = 1.5e-3 at
worst, measured 1.4e-6. A wrong channel order, a missing gate or a size baked into the graph is O(1)."""


def log_inputs(generator, height, width, seed=0):
    """Random log-domain inputs with a black block far wider than the gate's radius (the gate's job)."""
    rng = np.random.default_rng(seed)
    noisy = rng.gamma(0.7, 0.8, size=(1, 3, height, width)).astype(np.float32)
    noisy[..., 4 : height - 3, 5 : width // 2 + 20] = 0.0
    inputs = {"noisy": noisy, "features": rng.random((1, 7, height, width), dtype=np.float32)}
    if generator.config.refines:
        inputs["base"] = rng.gamma(0.7, 0.8, size=(1, 3, height, width)).astype(np.float32)
    return inputs


@pytest.mark.parametrize(
    "weights,base",
    [
        ("admc-small-pretrained.pt", "noisy"),
        ("admc-small-refiner.pt", "oidn"),
        ("admc-small-refiner-fast.pt", "oidn-fast"),
    ],
)
def test_exported_graphs_equal_torch_in_onnx_runtime_at_any_size(tmp_path, weights, base):
    written = export_onnx(WEIGHTS_DIR / weights, tmp_path / "onnx")  # what `admc-pipe export` calls
    assert sorted(p.name for p in written) == ["admc.json", "diffuse.onnx", "specular.onnx"]
    manifest = json.loads((tmp_path / "onnx" / "admc.json").read_text())
    generators = load_denoiser(WEIGHTS_DIR / weights, DenoiserOptions(dtype=torch.float32)).generators
    assert manifest["base"] == base and set(manifest["graphs"]) == set(generators) == {"diffuse", "specular"}
    assert manifest.get("base_quality") == BASE_QUALITIES.get(base)  # what OIDN runs at per branch, for a refiner
    assert manifest["gate_radius"] == {b: g.gate_radius for b, g in generators.items()}
    assert manifest["tile"]["halo"] == manifest["receptive_radius"] == 12  # 4 blocks: 1 + 8 + 1 + 2
    assert manifest["inputs"]["features"][:3] == ["normal.X", "normal.Y", "normal.Z"]
    for branch, generator in generators.items():
        session = onnxruntime.InferenceSession(
            str(tmp_path / "onnx" / manifest["graphs"][branch]), providers=["CPUExecutionProvider"]
        )
        assert [i.name for i in session.get_inputs()] == list(log_inputs(generator, 8, 8))
        for height, width in ((45, 70), (13, 9)):  # the trace saw 8x8; 13x9 is narrower than the black block
            inputs = log_inputs(generator, height, width)
            with torch.no_grad():
                expected = generator(*(torch.from_numpy(a) for a in inputs.values())).numpy()
            got = session.run(None, inputs)[0]
            assert got.shape == (1, 3, height, width)
            assert np.abs(got - expected).max() <= FLOAT32_LOG_TOLERANCE, (branch, height, width)
            if base == "noisy":  # where no light lies within the gate's radius, the output stays black
                assert np.all(got[..., 4 + 12 : height - 3 - 12, 5 + 12 : width // 2 + 20 - 12] == 0)


def test_export_needs_a_folder_and_real_weights(tmp_path):
    afile = tmp_path / "taken"
    afile.write_text("mine")
    refused(
        run("export", str(WEIGHTS_DIR / "admc-small-pretrained.pt"), "-o", str(afile)),
        f"{afile}: exists and is not a folder",
    )
    assert afile.read_text() == "mine"
    notes = tmp_path / "notes.pt"
    notes.write_text("not weights")
    refused(run("export", str(notes), "-o", str(tmp_path / "out")), f"{notes}: not a readable torch file")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("shipped", ["admc-small-pretrained.pt", "admc-small-refiner.pt"])
def test_noise_input_weights_export_the_noise_map_as_an_input_of_its_own(tmp_path, shipped):
    from conftest import noise_input_weights

    from admc.model.transforms import NOISE_STD_UNIT

    weights = noise_input_weights(tmp_path / "noise.pt", shipped)
    out = run("export", str(weights), "-o", str(tmp_path / "onnx"))  # the command, as a user runs it
    assert out.returncode == 0, out.stderr
    manifest = json.loads((tmp_path / "onnx" / "admc.json").read_text())
    assert manifest["noise_input"] is True and manifest["noise_std_unit"] == NOISE_STD_UNIT
    assert "noise" in manifest["inputs"] and len(manifest["inputs"]["features"]) == 7
    generators = load_denoiser(weights, DenoiserOptions(dtype=torch.float32)).generators
    for branch, generator in generators.items():
        session = onnxruntime.InferenceSession(
            str(tmp_path / "onnx" / manifest["graphs"][branch]), providers=["CPUExecutionProvider"]
        )
        names = ["noisy", "features", "noise"] + (["base"] if generator.config.refines else [])
        assert [i.name for i in session.get_inputs()] == names
        inputs = log_inputs(generator, 45, 70)
        inputs = {
            "noisy": inputs["noisy"],
            "features": inputs["features"],
            "noise": np.random.default_rng(1).random((1, 1, 45, 70), dtype=np.float32),
            **({"base": inputs["base"]} if "base" in inputs else {}),
        }
        with torch.no_grad():
            expected = generator(
                torch.from_numpy(inputs["noisy"]),
                torch.from_numpy(np.concatenate([inputs["features"], inputs["noise"]], axis=1)),
                torch.from_numpy(inputs["base"]) if "base" in inputs else None,
            ).numpy()
        got = session.run(None, inputs)[0]
        assert np.abs(got - expected).max() <= FLOAT32_LOG_TOLERANCE, branch


def test_weights_without_the_noise_input_export_as_before(tmp_path):
    export_onnx(WEIGHTS_DIR / "admc-small-pretrained.pt", tmp_path / "onnx")
    manifest = json.loads((tmp_path / "onnx" / "admc.json").read_text())
    assert not {"noise_input", "noise_std_unit"} & set(manifest) and "noise" not in manifest["inputs"]


def test_a_slim_generator_exports_and_equals_torch_in_onnx_runtime():
    """model.cfm_per_block = model.condition_layers = 1 (one CFM per block, one-conv condition nets) exports
    like the paper's layout; same tolerance (fewer convs on the chain, the same bound holds)."""
    from admc.model.inference.onnx_export import generator_graph
    from admc.model.nets.generator import Generator
    from admc.model.nets.settings import ModelSettings

    torch.manual_seed(0)
    generator = Generator(
        ModelSettings(
            channels=16,
            blocks=4,
            cond_channels=16,
            encoder_channels=32,
            input_skip=True,
            cfm_per_block=1,
            condition_layers=1,
        )
    ).eval()
    for p in generator.parameters():  # larger than the init's, so every layer changes the output
        torch.nn.init.normal_(p, std=0.1)
    session = onnxruntime.InferenceSession(generator_graph(generator), providers=["CPUExecutionProvider"])
    inputs = log_inputs(generator, 45, 70)
    with torch.no_grad():
        expected = generator(*(torch.from_numpy(a) for a in inputs.values())).numpy()
    assert np.abs(session.run(None, inputs)[0] - expected).max() <= FLOAT32_LOG_TOLERANCE
