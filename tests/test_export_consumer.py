"""examples/onnx_denoise.py, the reference consumer of `admc-pipe export`: from admc.json and the graphs alone
(it imports nothing of admc) it gives what `admc-pipe denoise --engine onnxruntime` gives, on a real render
with environment pixels and resolved regions, dim, with broken pixels, without depth and coverage, for
admc, admc+oidn and noise-input weights. A step admc.json left out or described wrongly shows here."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_cli import run
from test_export import FLOAT32_LOG_TOLERANCE

from admc.model.inference.input_layers import sanitize_layers
from admc.model.inference.exposure import exposure_gain
from admc.model.transforms import diffuse_forward, specular_forward
from admc.pipeline.stages.export import export_onnx
from admc.pipeline.weights import WEIGHTS_DIR
from admc.stores.exr import read_exr, write_exr

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "onnx_denoise.py"
OUTPUT_LAYERS = ["", "diffuse", "specular"]
TOLERANCE = FLOAT32_LOG_TOLERANCE
"""Both sides run the same graphs in ONNX Runtime float32; the example in tiles of 20 with the halo, admc on
the whole 64x48 image, so a conv may sum in another order: FLOAT32_LOG_TOLERANCE bounds that in the networks'
log domain, where everything else (the transforms, the clamp, the blend toward a resolved input, which moves
each pixel toward its input by a weight that window means of the same outputs decide) adds a few float32
ulps. So the branches are compared in that domain (network_domain), as the networks saw them."""


def network_domain(layers: dict[str, np.ndarray], *outputs: dict[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
    """Each output's denoised branches as their networks' outputs: at the exposure the networks saw, in each
    branch's log domain (a relative error, for dark pixels too)."""
    clean, _ = sanitize_layers(layers)
    gain = np.float32(exposure_gain(clean["diffuse"] + clean["specular"]))
    return [
        {
            "diffuse": diffuse_forward(out["diffuse"] * gain, clean["albedo"]),
            "specular": specular_forward(out["specular"] * gain),
        }
        for out in outputs
    ]


def scene(mi) -> dict:
    """A rough plastic ball and a black box on a checkered floor under a small area light, the sky seen above
    the floor: environment pixels, black albedo, silent pixels (no light, no variance)."""
    light = {"type": "rgb", "value": [60, 55, 50]}
    return {
        "type": "scene",
        "sensor": {
            "type": "perspective",
            "fov": 40,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0.6, 3], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 64, "height": 48, "rfilter": {"type": "box"}},
        },
        "floor": {
            "type": "rectangle",
            "bsdf": {
                "type": "diffuse",
                "reflectance": {"type": "checkerboard", "to_uv": mi.ScalarTransform4f().scale(6)},
            },
            "to_world": mi.ScalarTransform4f().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(1.5),
        },
        "ball": {
            "type": "sphere",
            "radius": 0.4,
            "center": [0.3, -0.1, 0],
            "bsdf": {"type": "roughplastic", "alpha": 0.1},
        },
        "box": {
            "type": "cube",
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}},
            "to_world": mi.ScalarTransform4f().translate([-0.7, -0.3, 0.6]).scale(0.2),
        },
        "light": {
            "type": "sphere",
            "radius": 0.1,
            "center": [-0.8, 1.0, 0.5],
            "emitter": {"type": "area", "radiance": light},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.4, 0.6]}},
    }


@pytest.fixture(scope="module")
def render(variant) -> dict[str, np.ndarray]:
    """64 spp: converged enough that keep_resolved moves part of the image back toward its input."""
    import mitsuba as mi

    from admc.pipeline.render import integrator
    from admc.pipeline.render.tasks import view_space_normals

    loaded = mi.load_dict(scene(mi))
    layers = integrator.render_buffers(loaded, 64, seed=3, split=True)
    layers["normal"] = view_space_normals(layers["normal"], loaded)
    assert (layers["coverage"] == 0).any() and (layers["coverage"] > 0).any()  # sky and surfaces
    return layers


def dim(layers):
    """1/64 of the exposure (variances 1/64^2): exposure normalisation scales it back up."""
    return {
        **layers,
        **{name: layers[name] / 64 for name in ("diffuse", "specular")},
        **{name: layers[name] / 64**2 for name in ("diffuse_var", "specular_var")},
    }


def broken(layers):
    """NaN and infinities where sanitising must repair them; +Inf radiance also caps the exposure gain at 1."""
    layers = {name: layer.copy() for name, layer in layers.items()}
    layers["diffuse"][5, 7] = [np.nan, np.inf, -np.inf]
    layers["albedo"][3, 3] = np.nan
    layers["normal"][4, 4, 0] = np.inf
    layers["specular"][9, 9, 1] = 1e30
    return layers


def without_depth_and_coverage(layers):
    return {name: layer for name, layer in layers.items() if name not in ("depth", "coverage")}


CASES = {
    "as rendered": lambda layers: layers,
    "dim": dim,
    "broken": broken,
    "without depth and coverage": without_depth_and_coverage,
}


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """Weights file -> its export folder, exported once per module (about 2 s each)."""
    folders: dict[Path, Path] = {}

    def export(weights: Path) -> Path:
        if weights not in folders:
            folders[weights] = tmp_path_factory.mktemp("onnx")
            export_onnx(weights, folders[weights])
        return folders[weights]

    return export


def compare(tmp_path, export_folder: Path, weights: Path, layers: dict[str, np.ndarray]) -> None:
    render_file = tmp_path / "render.exr"
    write_exr(render_file, layers, precision="float")
    admc = run(
        "denoise",
        str(render_file),
        "-o",
        str(tmp_path / "admc.exr"),
        "--engine",
        "onnxruntime",
        "--weights",
        str(weights),
    )
    assert admc.returncode == 0, admc.stderr
    example = subprocess.run(
        [
            sys.executable,
            str(EXAMPLE),
            str(export_folder),
            str(render_file),
            str(tmp_path / "example.exr"),
            "--tile",
            "20",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert example.returncode == 0, example.stderr
    want, got = read_exr(tmp_path / "admc.exr", OUTPUT_LAYERS), read_exr(tmp_path / "example.exr", OUTPUT_LAYERS)
    assert np.isfinite(got[""]).all() and np.array_equal(got[""], got["diffuse"] + got["specular"])
    want, got = network_domain(layers, want, got)
    for name in want:
        error = np.abs(got[name] - want[name]).max()
        assert error <= TOLERANCE, (name, error)
    assert "kept its detail" in admc.stdout  # keep_resolved moved part of the image: the comparison covers it


@pytest.mark.parametrize("case", list(CASES))
def test_the_example_denoises_as_admc_does(tmp_path, render, exported, case):
    layers = CASES[case](render)
    if case == "dim":
        assert exposure_gain(layers["diffuse"] + layers["specular"]) == 64.0
    weights = WEIGHTS_DIR / "admc-small-pretrained.pt"
    compare(tmp_path, exported(weights), weights, layers)


def test_the_example_runs_a_refiner_on_oidn_bases_as_admc_does(tmp_path, render, exported):
    weights = WEIGHTS_DIR / "admc-small-refiner.pt"
    compare(tmp_path, exported(weights), weights, dim(render))


def test_the_example_feeds_the_noise_map_as_admc_does(tmp_path, render, exported):
    from conftest import noise_input_weights

    weights = noise_input_weights(tmp_path / "noise.pt")
    compare(tmp_path, exported(weights), weights, dim(render))


def test_the_example_blends_with_oidn_as_admc_does(tmp_path, render, exported):
    """Weights that ship an OIDN blend (train.oidn_blend): admc.json carries the shares and the example blends
    each branch with OIDN's output as `admc-pipe denoise` does."""
    from admc.stores.checkpoints import OIDN_BLEND, export_weights, load_weights

    shipped = load_weights(WEIGHTS_DIR / "admc-small-pretrained.pt")
    weights = tmp_path / "blended.pt"
    export_weights(weights, shipped["branches"], {**shipped["metadata"], OIDN_BLEND: {"diffuse": 0.4, "specular": 0.7}})
    folder = exported(weights)
    assert json.loads((folder / "admc.json").read_text())["oidn_blend"]["shares"] == {"diffuse": 0.4, "specular": 0.7}
    compare(tmp_path, folder, weights, render)


@pytest.mark.parametrize("network", ["standard", "large"])
def test_the_example_blends_with_a_fine_tuned_oidn_as_admc_does(tmp_path, render, exported, network):
    """Weights that ship OIDN fine-tuned with them (train.oidn_minutes): the export writes its weights as OIDN's
    own TZA files, admc.json names them, and the example's OIDN runs them as `admc-pipe denoise` does; a large
    diffuse network (train.oidn_network) on guides OIDN prefilters, as admc.json says."""
    from admc.model.nets.oidn_unet import oidn_unet
    from admc.stores.checkpoints import OIDN_BLEND, export_weights, load_weights, read_oidn_networks

    shipped = load_weights(WEIGHTS_DIR / "admc-small-pretrained.pt")
    partner = {b: oidn_unet(b, network).state_dict() for b in ("diffuse", "specular")}
    last = "dec_conv1c.bias" if network == "large" else "dec_conv0.bias"
    partner["diffuse"][last] += 0.05  # not OIDN's own: the files must be what runs
    weights = tmp_path / "partner.pt"
    metadata = {**shipped["metadata"], OIDN_BLEND: {"diffuse": 0.4, "specular": 0.7}}
    export_weights(weights, shipped["branches"], metadata, oidn_networks=partner)
    assert set(read_oidn_networks(weights)) == {"diffuse", "specular"}
    folder = exported(weights)
    blend = json.loads((folder / "admc.json").read_text())["oidn_blend"]
    assert blend["weights"] == {"diffuse": "oidn-diffuse.tza", "specular": "oidn-specular.tza"}
    assert blend["prefiltered_guides"] == (["diffuse"] if network == "large" else [])
    assert all((folder / name).is_file() for name in blend["weights"].values())
    compare(tmp_path, folder, weights, render)


def test_the_example_imports_nothing_of_admc():
    """What it does follows from admc.json, not from admc's code."""
    imported = set()
    for node in ast.walk(ast.parse(EXAMPLE.read_text())):
        if isinstance(node, ast.Import):
            imported |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add((node.module or "").split(".")[0])
    assert imported <= {
        "__future__",
        "argparse",
        "json",
        "math",
        "pathlib",
        "numpy",
        "onnxruntime",
        "OpenEXR",
        "scipy",
        "pyoidn",
    }, imported
