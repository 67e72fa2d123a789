"""User errors as a person meets them through `admc-pipe`: one message naming the file or key and the problem,
a non-zero exit, no traceback; and bugs (anything but admc.errors.AdmcError) keep theirs."""

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import tomllib
from pathlib import Path

import pytest
from test_cli import ADMC, _oidn_style_input, run
from test_train_stage import flags, settings

from admc.model.nets.settings import ModelSettings
from admc.pipeline.config import load_config
from admc.pipeline.weights import WEIGHTS_DIR
from admc.stores.checkpoints import export_weights, load_checkpoint, load_weights

SHIPPED = WEIGHTS_DIR / "admc-small-pretrained.pt"


def refused(out, *needles):
    """The run failed with exit 2 and one message holding every needle, and no traceback."""
    assert out.returncode == 2, (out.returncode, out.stdout, out.stderr)
    assert "Traceback" not in out.stderr + out.stdout, out.stderr
    for needle in needles:
        assert needle in out.stderr, (needle, out.stderr)


def garbage_files(folder: Path) -> dict[Path, str]:
    """A text file, random bytes and a truncated real checkpoint named like one, each with its reason."""
    text = folder / "notes.pt"
    text.write_text("these are my notes, not weights\n")
    noise = folder / "noise.pt"
    noise.write_bytes(bytes(range(256)) * 8)
    truncated = folder / "checkpoint.pt"
    truncated.write_bytes(SHIPPED.read_bytes()[:5000])
    return {text: "not in torch's save format", noise: "not in torch's save format", truncated: "truncated or damaged"}


@pytest.fixture(scope="module")
def tiny_workdir(tmp_path_factory):
    """A workdir whose patch store (test_train_stage's tiny corpus) is built, so `train` starts at once."""
    workdir = tmp_path_factory.mktemp("errors")
    out = subprocess.run([ADMC, "dataset", *flags(settings(workdir))], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    return workdir


def test_a_bare_value_error_is_a_bug_and_keeps_its_traceback():
    from admc.cli.app import _user_errors

    def numpy_bug():
        raise ValueError("operands could not be broadcast together")

    with pytest.raises(ValueError, match="broadcast"):
        _user_errors(numpy_bug)()


def test_admc_debug_shows_the_traceback_of_a_user_error(tmp_path):
    env = {**os.environ, "ADMC_DEBUG": "1"}
    out = subprocess.run(
        [ADMC, "config", "--config", str(tmp_path)], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode != 0 and "Traceback" in out.stderr and "ConfigError" in out.stderr


def test_denoise_output_naming_a_directory(tmp_path):
    frame = _oidn_style_input(tmp_path)
    folder = tmp_path / "out.exr"
    folder.mkdir()
    out = run("denoise", str(frame), "-o", str(folder), "--weights", str(SHIPPED))
    refused(out, f"{folder}: is a directory")
    assert list(folder.iterdir()) == [] and not list(tmp_path.glob(".*tmp*"))


def test_denoise_with_an_engine_not_offered(tmp_path):
    frame = _oidn_style_input(tmp_path)
    refused(
        run("denoise", str(frame), "--engine", "tensorrt", "--weights", str(SHIPPED)),
        "--engine must be one of",
        "got 'tensorrt'",
    )
    assert not (tmp_path / "frame.denoised.exr").exists()
    out = run("denoise", str(frame), "--engine", "onnxruntime", "--weights", str(SHIPPED))
    assert out.returncode == 0 and "onnxruntime float32" in out.stdout, out.stderr  # the engine it ran in
    assert (tmp_path / "frame.denoised.exr").is_file()


def test_denoise_with_an_ensemble_size_not_offered(tmp_path):
    frame = _oidn_style_input(tmp_path)
    out = run("denoise", str(frame), "--ensemble", "3", "--weights", str(SHIPPED))
    refused(out, "--ensemble must be one of 1, 2, 4, 8, got 3")
    assert not (tmp_path / "frame.denoised.exr").exists()


@pytest.mark.parametrize("device", ["foo", "cuda:99"])
def test_denoise_on_an_unknown_device(tmp_path, device):
    frame = _oidn_style_input(tmp_path)
    out = run("denoise", str(frame), "--device", device, "--weights", str(SHIPPED))
    refused(out, f"device {device!r}")
    assert not (tmp_path / "frame.denoised.exr").exists()


def test_weights_that_are_not_a_checkpoint(tmp_path):
    frame = _oidn_style_input(tmp_path)
    for bad, reason in garbage_files(tmp_path).items():
        for command in (["denoise", str(frame)], ["eval", "--set", f"run.workdir='{tmp_path / 'w'}'"]):
            out = run(*command, "--weights", str(bad))
            refused(out, f"{bad}: not a readable torch file: ", reason)
            assert "weights_only" not in out.stderr  # torch's unsafe advice is not passed on


def test_train_init_from_garbage_is_refused_before_the_dataset_is_built(tmp_path):
    for bad, reason in garbage_files(tmp_path).items():
        out = run("train", "--stage", "finetune", "--init", str(bad), *flags(settings(tmp_path / "w")))
        refused(out, f"{bad}: not a readable torch file: ", reason)
        assert not (tmp_path / "w" / "renders").exists()
        assert "weights_only" not in out.stderr


def _mislabelled_weights(path: Path, model: ModelSettings) -> Path:
    """The shipped weights' tensors under metadata that claims the architecture `model`."""
    shipped = load_weights(SHIPPED)
    export_weights(path, shipped["branches"], {**shipped["metadata"], "model": dataclasses.asdict(model)})
    return path


def test_weights_whose_tensors_do_not_match_their_metadata(tiny_workdir, tmp_path):
    tiny = load_config(None, settings(tiny_workdir)).model
    weights = _mislabelled_weights(tmp_path / "mislabelled.pt", tiny)
    frame = _oidn_style_input(tmp_path)
    out = run("denoise", str(frame), "--weights", str(weights))
    refused(
        out,
        f"{weights}: diffuse generator weights do not fit the architecture its own metadata describes",
        "tensor(s) of another shape (first ",
    )
    out = run("train", "--stage", "finetune", "--init", str(weights), *flags(settings(tiny_workdir)))
    refused(
        out,
        f"{weights}: diffuse generator weights do not fit the configured architecture",
        "tensor(s) of another shape (first ",
    )


def test_config_naming_a_directory_or_non_utf8_file(tmp_path):
    refused(run("config", "--config", str(tmp_path)), f"config file {tmp_path} is a directory")
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes('[run]\nworkdir = "/tmp/café"\n'.encode("latin-1"))
    refused(run("config", "--config", str(latin1)), f"config file {latin1} is not UTF-8")


def test_printed_config_round_trips(tmp_path):
    overrides = [
        "--set",
        "run.workdir='/tmp/a \"quoted\" \\\\ dir é'",
        "--set",
        "render.spp=[2, 8]",
        "--set",
        "corpus.xml_dirs=['scenes/a', 'b']",
        "--set",
        "train.lr_d=3e-05",
    ]
    first = run("config", *overrides)
    assert first.returncode == 0, first.stderr
    assert first.stdout.startswith("[corpus]\n") and "\n[run]\n" in first.stdout
    saved = tmp_path / "x.toml"
    saved.write_text(first.stdout)
    second = run("config", "--config", str(saved))
    assert second.returncode == 0, second.stderr
    assert second.stdout == first.stdout
    loaded = load_config(saved)
    assert loaded == load_config(None, overrides[1::2])
    assert loaded.run.workdir == '/tmp/a "quoted" \\\\ dir é'  # a TOML literal string keeps both
    assert loaded.corpus.xml_dirs == ("scenes/a", "b") and loaded.render.spp == (2, 8)
    assert tomllib.loads(first.stdout)["train"]["lr_d"] == 3e-05


def test_a_batch_carries_on_past_a_bad_file_and_fails_at_the_end(tmp_path):
    for name in ("a", "c"):
        (tmp_path / name).mkdir()
    good = [_oidn_style_input(tmp_path / name) for name in ("a", "c")]
    bad = tmp_path / "bad.exr"
    bad.write_text("not an image")
    out = run("denoise", str(good[0]), str(bad), str(good[1]), "--weights", str(SHIPPED))
    written = [path.with_name("frame.denoised.exr") for path in good]
    refused(out, "1 of 3 inputs not denoised", f"{bad}: not an OpenEXR file", f"written: {written[0]}, {written[1]}")
    assert all(path.is_file() for path in written)


def _interrupt_at(workdir: Path, step: int, checkpoint_every: int):
    """Start a long `train` with data-loader workers, and once it has logged `step` send SIGINT to its whole
    process group, as Ctrl-C in a terminal does; return its exit code and stderr. The child gets SIGINT's
    default action back: a suite started in the background of a script inherits it ignored, and the
    training would then never stop."""
    items = settings(workdir, steps=10_000) + [f"train.checkpoint_every={checkpoint_every}", "train.num_workers=2"]
    process = subprocess.Popen(
        [ADMC, "train", *flags(items)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    seen = []
    for line in process.stderr:
        seen.append(line)
        if line.startswith(f"pretrain step {step}/"):
            os.killpg(process.pid, signal.SIGINT)
            break
    rest = process.stderr.read()
    process.wait(timeout=120)
    return process.returncode, "".join(seen) + rest


def test_ctrl_c_during_train_says_what_was_saved_and_how_to_resume(tiny_workdir):
    checkpoint = tiny_workdir / "train" / "pretrain" / "checkpoint.pt"
    code, stderr = _interrupt_at(tiny_workdir, step=1, checkpoint_every=1000)
    assert code == 130 and "Traceback" not in stderr, stderr
    assert "interrupted: no checkpoint written yet" in stderr and str(checkpoint) in stderr
    assert not checkpoint.exists()

    code, stderr = _interrupt_at(tiny_workdir, step=3, checkpoint_every=2)
    assert code == 130 and "Traceback" not in stderr, stderr
    step = load_checkpoint(checkpoint)["step"]
    assert step >= 2
    assert f"interrupted: checkpoint {checkpoint} holds step {step}" in stderr
    assert "run the same command to resume from it" in stderr

    out = run("train", *flags(settings(tiny_workdir, steps=step + 1)))
    assert out.returncode == 0, out.stderr
    assert f"resuming pretrain from {checkpoint} at step {step}" in out.stdout + out.stderr
    assert load_checkpoint(checkpoint)["step"] == step + 1


def test_a_damaged_cache_manifest_is_named(tiny_workdir, tmp_path):
    """Caught by the CLI's old catch-all of ValueError: this guards that catching only AdmcError keeps it so."""
    entry = next((tiny_workdir / "cache").glob("*/*/_task.json")).parent
    copy = tmp_path / "cache" / entry.parent.name / entry.name
    shutil.copytree(entry, copy)
    manifest = copy / "_task.json"
    manifest.write_text(manifest.read_text()[:20])
    refused(run("cache", "--set", f"run.workdir='{tmp_path}'"), f"{manifest}: not valid JSON")


def test_a_damaged_render_sidecar_is_rendered_again(tiny_workdir, tmp_path):
    shutil.copytree(tiny_workdir / "cache" / "render", tmp_path / "cache" / "render")
    sidecar = next((tmp_path / "cache" / "render").glob("*/render.json"))
    whole = sidecar.read_text()
    sidecar.write_text(whole[:20])
    out = run("render", *flags(settings(tmp_path)))
    assert out.returncode == 0, out.stderr
    assert "(1 rendered now" in out.stdout
    rendered, before = json.loads(sidecar.read_text()), json.loads(whole)
    assert (rendered["scene_id"], rendered["spp"]) == (before["scene_id"], before["spp"])


def test_noise_input_weights_name_the_variance_layer_an_input_lacks(tmp_path):
    import numpy as np
    from conftest import noise_input_weights

    from admc.stores.exr import read_exr, write_exr

    weights = noise_input_weights(tmp_path / "noise.pt")
    frame = _oidn_style_input(tmp_path)  # OIDN-style files carry no variance
    out = run("denoise", str(frame), "--weights", str(weights))
    refused(
        out, f"{frame}: lacks layer(s) diffuse_var, which the weights {weights} read", "--set model.noise_input=false"
    )
    assert not list(tmp_path.glob("*denoised*"))

    rng = np.random.default_rng(0)
    layers = {
        name: rng.uniform(0, 1, (8, 8, 3)).astype(np.float32)
        for name in ("diffuse", "specular", "albedo", "normal", "diffuse_var")
    }
    render = tmp_path / "render.exr"
    write_exr(render, layers, precision="float")
    refused(
        run("denoise", str(render), "--weights", str(weights)),
        f"{render}: lacks layer(s) specular_var, which the weights {weights} read",
    )
    layers["specular_var"] = layers["diffuse_var"]
    write_exr(render, layers, precision="float")
    for engine in ("torch", "onnxruntime", "openvino"):
        target = tmp_path / f"render.{engine}.exr"
        out = run("denoise", str(render), "--weights", str(weights), "--engine", engine, "-o", str(target))
        assert out.returncode == 0, out.stderr
        assert np.isfinite(read_exr(target)["diffuse"]).all()
