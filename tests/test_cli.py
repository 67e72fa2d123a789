"""The command line as a person meets it: --help, wrong arguments, missing files."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ADMC = str(Path(__file__).resolve().parents[1] / ".venv" / "bin" / "admc-pipe")


def run(*args, cwd=None):
    return subprocess.run([ADMC, *args], capture_output=True, text=True, cwd=cwd, timeout=120)


def test_help_lists_every_command():
    out = run("--help")
    assert out.returncode == 0
    for command in ("render", "dataset", "tile", "train", "eval", "denoise", "cache", "config"):
        assert command in out.stdout
    assert "not built" not in out.stdout


@pytest.mark.parametrize("command", ["render", "dataset", "tile", "train", "eval", "denoise", "cache", "config"])
def test_every_command_has_help(command):
    out = run(command, "--help")
    assert out.returncode == 0 and "Usage" in out.stdout


HEAVY = ("torch", "mitsuba", "openvino")
"""Modules that take seconds to import: the CLI must not load them before it needs them."""


def invoke_in_fresh_python(
    *calls: list[str], cwd=None, watch: tuple[str, ...] = HEAVY
) -> list[tuple[int, list[str], str]]:
    """Run each call's CLI arguments in turn in one new interpreter; per call its exit code, the `watch`ed
    packages loaded so far (a package counts as loaded when it or any of its modules is) and its output."""
    code = (
        "import json, sys; from typer.testing import CliRunner; from admc.cli.app import app\n"
        "for args in json.loads(sys.argv[1]):\n"
        "    result = CliRunner().invoke(app, args)\n"
        f"    loaded = [w for w in {watch!r} if any(m == w or m.startswith(w + '.') for m in sys.modules)]\n"
        "    print(json.dumps([result.exit_code, loaded, result.output]))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, json.dumps(calls)], capture_output=True, text=True, timeout=120, cwd=cwd
    )
    assert out.returncode == 0, out.stderr
    return [tuple(json.loads(line)) for line in out.stdout.splitlines()]


def test_the_cli_and_its_config_load_without_torch():
    """--help, `config` and argument errors answer in well under a second only if importing the CLI (and
    the config checks it runs) leaves torch alone: torch alone takes about 2 s to import."""
    code = f"import sys, admc.cli.app; print(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_denoise_names_a_bad_input_without_loading_torch(tmp_path):
    """A missing or unreadable file is reported before the weights (and torch) are loaded."""
    (tmp_path / "broken.exr").write_bytes(b"not an EXR")
    results = invoke_in_fresh_python(
        ["denoise", str(tmp_path / "missing.exr")], ["denoise", str(tmp_path / "broken.exr")]
    )
    assert [(code, loaded) for code, loaded, _ in results] == [(2, []), (2, [])]


TRAINING_STACK = ("admc.model.training", "tensorboard", "zarr")
"""What only training needs: denoising a file loads none of it (the checkpoint and weights file names live
with their format in stores/checkpoints.py, the [train] settings in model/train_settings.py)."""


def test_denoise_loads_no_training_module(tmp_path):
    ((code, loaded, output),) = invoke_in_fresh_python(
        ["denoise", str(_oidn_style_input(tmp_path))], watch=("torch", *TRAINING_STACK)
    )
    assert code == 0, output
    assert (tmp_path / "frame.denoised.exr").is_file()
    assert loaded == ["torch"], f"denoise loaded {loaded[1:]}"


@pytest.mark.parametrize("command", ["render", "dataset", "tile", "train", "eval", "cache"])
def test_a_bad_config_is_named_before_torch_loads(command, tmp_path):
    """Each command checks its config before importing its stage (torch, Mitsuba: seconds)."""
    cases = {
        "missing.toml": [command, "--config", str(tmp_path / "missing.toml")],
        "train.nope": [command, "--set", "train.nope=1"],
    }
    results = invoke_in_fresh_python(*cases.values(), cwd=tmp_path)
    for named, (code, loaded, output) in zip(cases, results, strict=True):
        assert code == 2 and loaded == [] and named in output


def _oidn_style_input(folder: Path) -> Path:
    from admc.stores.exr import write_exr

    rng = np.random.default_rng(0)
    for role, lo in (("hdr", 0.0), ("alb", 0.0), ("nrm", 0.0)):  # normals facing the camera
        write_exr(folder / f"frame.{role}.exr", {"": rng.uniform(lo, 1.0, (8, 8, 3)).astype(np.float32)})
    return folder / "frame.hdr.exr"


def test_denoise_checks_its_input_and_output_before_loading_weights(tmp_path):
    assert run("denoise").returncode == 2
    out = run("denoise", str(tmp_path / "missing.exr"), "--weights", str(tmp_path / "w.pt"))
    assert out.returncode == 2 and "missing.exr" in out.stderr and "Traceback" not in out.stderr
    assert "weights:" not in out.stdout, "a missing input is reported before any model is loaded"
    frame = _oidn_style_input(tmp_path)
    out = run("denoise", str(frame), "-o", str(tmp_path / "out.png"), "--weights", str(tmp_path / "w.pt"))
    assert out.returncode == 2 and "out.png: the output must be an .exr file" in out.stderr
    out = run("denoise", str(frame), "--weights", str(tmp_path / "w.pt"))
    assert out.returncode == 2 and "w.pt" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "frame.denoised.exr").exists()


def test_wrong_option_is_rejected():
    out = run("render", "--no-such-option")
    assert out.returncode == 2
    assert "no-such-option" in out.stderr


@pytest.mark.parametrize(
    "args, needle",
    [
        (["config", "--config", "missing.toml"], "missing.toml"),
        (["config", "--set", "render.sppp=4"], "render.sppp"),
        (["render", "--set", "render.variant=no_such_variant"], "no_such_variant"),
    ],
)
def test_bad_input_is_one_clear_line(tmp_path, args, needle):
    out = run(*args, cwd=tmp_path)
    assert out.returncode == 2
    assert needle in out.stderr
    assert "Traceback" not in out.stderr


def test_config_prints_resolved_values(tmp_path):
    out = run("config", "--set", "render.spp=[2, 8]", cwd=tmp_path)
    assert out.returncode == 0
    assert "spp = [2, 8]" in out.stdout


def test_several_configs_overlay_in_order(tmp_path):
    # a recipe file and the user's own: `--config configs/domain.toml --config mine.toml`
    (tmp_path / "recipe.toml").write_text("[render]\nreference_spp = 256\nmax_depth = 5\n")
    (tmp_path / "mine.toml").write_text("[render]\nreference_spp = 1024\n")
    out = run("config", "--config", "recipe.toml", "--config", "mine.toml", "--set", "render.spp=[2, 8]", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "reference_spp = 1024" in out.stdout and "max_depth = 5" in out.stdout and "spp = [2, 8]" in out.stdout
