"""Numerical stability: stiff and extreme images through the real model, OIDN, the metrics and the report.

Fireflies of 1e6+, NaN/Inf pixels, black images, white albedo, environment-only pixels, 1 spp and odd
sizes must give finite outputs, finite metrics and a report, never a crash or a silent NaN.
"""
import dataclasses
import json

import numpy as np
import pytest
import torch

from admc.model.denoiser import load_denoiser
from admc.model.settings import ModelSettings
from admc.model.generator import Generator
from admc.model.transforms import transform_spec
from admc.pipeline.denoisers import NoisyInput, OidnDenoiser
from admc.pipeline.evaluate import TestImage, evaluate
from admc.stores.checkpoints import export_weights
from admc.stores.exr import write_exr

TINY = ModelSettings(channels=8, blocks=1, cond_channels=8, encoder_channels=8, critic_channels=4)


def scene(h, w, rng, *, spp=1, specular=True):
    layers = {"diffuse": rng.exponential(0.3, (h, w, 3)).astype(np.float32),
              "albedo": rng.uniform(0.05, 0.9, (h, w, 3)).astype(np.float32),
              "normal": np.tile(np.array([0, 0, 1], np.float32), (h, w, 1)),
              "depth": rng.uniform(1, 3, (h, w, 1)).astype(np.float32),
              "coverage": np.ones((h, w, 1), np.float32)}
    if specular:
        layers["specular"] = rng.exponential(0.05, (h, w, 3)).astype(np.float32)
    return layers


def extreme_cases(rng):
    fireflies = scene(48, 40, rng)
    fireflies["diffuse"][5, 7] = 3e6
    fireflies["specular"][20, 20] = 1e9
    poisoned = scene(33, 31, rng)
    poisoned["diffuse"][0, :4] = np.nan
    poisoned["specular"][3, 3] = np.inf
    poisoned["normal"][4, 4] = np.nan
    black = {k: np.zeros_like(v) for k, v in scene(32, 32, rng).items()}
    white = scene(32, 32, rng)
    white["albedo"][:] = 1.0
    environment = scene(32, 32, rng, specular=False)
    environment["coverage"][:] = 0.0
    environment["depth"][:] = 0.0
    environment["normal"][:] = 0.0
    environment["albedo"][:] = 1.0
    return {"fireflies": fireflies, "poisoned": poisoned, "black": black, "white-albedo": white,
            "environment-only": environment, "one-pixel": scene(1, 1, rng), "odd-127x129": scene(127, 129, rng),
            "strip-37x4000": scene(37, 4000, rng, specular=False)}


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    torch.manual_seed(0)
    weights = tmp_path_factory.mktemp("w") / "tiny.pt"
    branches = {b: {"generator": Generator(TINY.generator_config()).state_dict(),
                    "critic": torch.nn.Linear(1, 1).state_dict()} for b in ("diffuse", "specular")}
    export_weights(weights, branches, {"model": dataclasses.asdict(TINY), "transform": transform_spec()})
    return load_denoiser(weights, tile=64)


def test_model_denoises_every_extreme_case_to_finite_values(model):
    for name, layers in extreme_cases(np.random.default_rng(0)).items():
        result = model(layers)
        assert result.image.shape == layers["diffuse"].shape, name
        assert np.isfinite(result.image).all(), name
        assert (result.image >= 0).all(), name
    poisoned = model(extreme_cases(np.random.default_rng(0))["poisoned"])
    assert poisoned.sanitized, "repairs are reported, not silent"


def test_eval_on_extreme_cases_gives_finite_metrics_and_complete_tables(model, tmp_path):
    rng = np.random.default_rng(1)
    images = []
    for name, layers in extreme_cases(rng).items():
        folder = tmp_path / "renders" / name
        folder.mkdir(parents=True)
        reference = {k: np.nan_to_num(v, nan=0.0, posinf=1.0) for k, v in layers.items()}
        write_exr(folder / "reference.exr", reference, precision="float")
        write_exr(folder / "spp0001.exr", layers, precision="float")
        images.append(TestImage(name, 1, folder / "spp0001.exr", folder / "reference.exr", 0.01))
    result = evaluate(images, [NoisyInput(), OidnDenoiser(quality="fast"), model], tmp_path / "eval",
                      progress=False, repeats=1, warmup=0)
    assert len(result.records) == 3 * len(images)
    for record in result.records:
        assert np.isfinite([record.relmse, record.psnr, record.one_minus_ssim]).all(), record
    table = json.loads(result.files["results_json"].read_text())["table"]
    for row in table:
        assert all(np.isfinite(v) for v in row["average"].values())
    poisoned = [r for r in result.records if r.scene_id == "poisoned" and r.method == "noisy"]
    assert poisoned[0].nonfinite > 0, "the noisy input's NaN/Inf are counted in the records"


def test_real_one_spp_renders_through_eval(model, variant, tmp_path):
    """1 spp from the real integrator (the stiffest input a user can render), not a synthetic stand-in."""
    from admc.pipeline.config import load_config
    from admc.pipeline.evaluate import find_test_images
    from admc.pipeline.stages import render_corpus

    cfg = load_config(None, [f"run.workdir='{tmp_path}'", "run.scheduler=sync", "render.resolution=[32, 32]",
                             "render.spp=[1]", "render.reference_spp=64", "corpus.n_scenes=2"])
    images = find_test_images(render_corpus(cfg, progress=False).renders_dir)
    assert {t.spp for t in images} == {1}
    result = evaluate(images, [NoisyInput(), OidnDenoiser(), model], tmp_path / "eval", progress=False,
                      repeats=1, warmup=0)
    for record in result.records:
        assert np.isfinite([record.relmse, record.psnr, record.one_minus_ssim]).all(), record
        assert record.nonfinite == 0 and np.isfinite(np.load(record.image)).all(), record
    row = {r.method: r for r in result.table}
    assert row["oidn"].average["relmse"] < row["noisy"].average["relmse"]
