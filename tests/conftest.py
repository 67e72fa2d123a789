"""Shared fixtures. Tests render with the best JIT variant this machine has (llvm_ad_rgb on CI)."""

from collections import defaultdict

import pytest

from admc.pipeline.render.variants import use_variant


def pytest_terminal_summary(terminalreporter):
    """One line per reason some tests did not run, naming them: a `make test` that passes without its
    browser (or GPU) tests says so, instead of a bare "3 skipped"."""
    skipped = defaultdict(list)
    for report in terminalreporter.stats.get("skipped", []):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        skipped[reason.removeprefix("Skipped: ")].append(report.nodeid.rpartition("::")[2])
    for reason, names in skipped.items():
        terminalreporter.write_line(f"skipped {len(names)} ({', '.join(names)}): {reason}")


@pytest.fixture(scope="session")
def variant() -> str:
    """Activate the render variant once per test session (like Mitsuba's own variant fixtures)."""
    return use_variant("auto")


@pytest.fixture(params=["float32", "bfloat16"])
def inference_dtype(request):
    """Both precisions the networks infer in, on every CPU: `auto` picks bf16 autocast where the CPU has
    hardware bf16 (AVX512-BF16, AMX) and float32 elsewhere, so a test that took the default would
    check another thing on each machine. bf16 autocast runs on any x86 CPU (emulated, slower)."""
    from admc.model.precision import PRECISIONS

    return PRECISIONS[request.param]


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """Tiny nets gain nothing from intra-op threads, and on a shared 2-core machine OpenMP's spinning
    threads made the network tests ~15x slower: one thread for the session, restored after."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def tiny_store_overrides(workdir, size: int, patch: int) -> list[str]:
    """The `--set` values of a 4-scene corpus rendered at size x size (seconds to build)."""
    return [
        f"run.workdir='{workdir}'",
        "run.scheduler=sync",
        f"render.resolution=[{size}, {size}]",
        "render.spp=[2, 4]",
        "render.reference_spp=16",
        "corpus.n_scenes=4",
        f"tile.patch_size={patch}",
        "tile.crops_per_scene=3",
        "tile.split=[0.5, 0.5, 0.0]",
    ]


def preset(name: str):
    """The [model] and [train] sections of a shipped config (configs/NAME.toml) as the CLI loads it:
    the presets exist only as TOML."""
    from importlib import resources

    from admc.pipeline.config import load_config

    cfg = load_config(None if name == "default" else resources.files("admc.configs").joinpath(f"{name}.toml"))
    return cfg.model, cfg.train


def build_tiny_store(workdir, size: int, patch: int, extra: list[str] = ()):
    """A real patch store from a 4-scene corpus rendered at size x size (seconds): the tests' data;
    `extra` adds `--set` values (e.g. tile.noise_maps=true)."""
    from admc.pipeline.config import load_config
    from admc.pipeline.stages.dataset import build_dataset

    cfg = load_config(None, [*tiny_store_overrides(workdir, size, patch), *extra])
    return build_dataset(cfg, progress=False).store


def noise_input_weights(path, shipped: str = "admc-small-pretrained.pt", seed: int = 0):
    """Weights with model.noise_input, written to `path`: the shipped file `shipped` widened as fine-tuning
    widens it, then given random weights on the noise channel as large as the other channels' (zero ones
    would hide a noise map that went missing or to the wrong place)."""
    import dataclasses

    import torch

    from admc.model.nets.settings import ModelSettings
    from admc.model.training.resume import with_noise_input
    from admc.pipeline.weights import WEIGHTS_DIR
    from admc.stores.checkpoints import export_weights, load_weights

    saved = load_weights(WEIGHTS_DIR / shipped)
    model = dataclasses.replace(ModelSettings.from_saved(saved["metadata"]["model"]), noise_input=True)
    generator = torch.Generator().manual_seed(seed)
    branches = {}
    for branch, nets in saved["branches"].items():
        state = with_noise_input({k: v.float() for k, v in nets["generator"].items()}, model)
        first = state["encoder.layers.0.weight"]
        first[:, 7] = torch.randn(first[:, 7].shape, generator=generator) * float(first[:, :7].std())
        branches[branch] = {**nets, "generator": state}
    export_weights(path, branches, {**saved["metadata"], "model": dataclasses.asdict(model)})
    return path
