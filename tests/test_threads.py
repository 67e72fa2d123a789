"""torch's OpenMP pool kept out of other engines' way: glue around an exported graph runs inline, and
libgomp's spin after each parallel region is cut when admc is imported first (admc/__init__.py)."""

import os
import subprocess
import sys

import pytest
import torch
from test_engines import SHIPPED
from test_inference import render_layers

from admc.common.threads import torch_inline
from admc.model.inference.denoiser import load_denoiser
from admc.model.inference.options import DenoiserOptions


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_torch_inline_runs_on_one_thread_and_restores_the_pool(two_threads):
    with torch_inline():
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), torch_inline():
        raise RuntimeError("a failed denoise")
    assert torch.get_num_threads() == 2


class ThreadsSeen:
    """A real generator (torch module or exported graph), recording torch's thread count at each call."""

    def __init__(self, generator):
        self.generator, self.seen = generator, []

    def __call__(self, *inputs):
        self.seen.append(torch.get_num_threads())
        return self.generator(*inputs)


@pytest.mark.parametrize("engine, threads_inside", [("openvino", 1), ("torch", 2)])
def test_only_the_exported_engines_run_torch_inline(two_threads, engine, threads_inside):
    denoiser = load_denoiser(SHIPPED, DenoiserOptions(engine=engine, dtype=torch.float32))
    recorder = denoiser.generators["diffuse"] = ThreadsSeen(denoiser.generators["diffuse"])
    denoiser(render_layers(24, 32, seed=5))
    assert recorder.seen and set(recorder.seen) == {threads_inside}
    assert torch.get_num_threads() == 2


@pytest.mark.parametrize("preset, expected", [(None, "10000"), ("123", "123")])
def test_importing_admc_sets_the_spin_count_unless_the_user_did(preset, expected):
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    if preset is not None:
        env["GOMP_SPINCOUNT"] = preset
    code = "import os, admc; print(os.environ['GOMP_SPINCOUNT'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == expected
