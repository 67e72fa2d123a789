"""`admc-pipe train` as a user runs it: pretrain on a tiny corpus, resume, then fine-tune from its weights."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from admc.pipeline.config import load_config
from admc.pipeline.weights import WEIGHTS_DIR, shipped_weights
from admc.stores.checkpoints import load_checkpoint, load_weights

ADMC = str(Path(sys.executable).parent / "admc-pipe")
SHIP_WEIGHTS = Path(__file__).resolve().parents[1] / "scripts" / "ship_weights.py"


def settings(workdir, steps=4):
    return [
        f"run.workdir='{workdir}'",
        "run.scheduler=sync",
        "render.resolution=[64, 64]",
        "render.spp=[2, 4]",
        "render.reference_spp=16",
        "corpus.n_scenes=3",
        "tile.patch_size=32",
        "tile.crops_per_scene=2",
        "tile.split=[0.5, 0.5, 0.0]",
        "tile.seed=1",
        "model.channels=8",
        "model.blocks=1",
        "model.cond_channels=8",
        "model.encoder_channels=8",
        "model.critic_channels=4",
        f"train.steps={steps}",
        "train.l1_warmup_steps=1",
        "train.critic_only_steps=1",
        "train.head_tail_start_step=0",
        "train.val_every=2",
        "train.val_patches=2",
        "train.checkpoint_every=2",
        "train.log_every=1",
        "train.threads=1",
    ]


def cli(*args):
    return subprocess.run([ADMC, *args], capture_output=True, text=True, timeout=600)


def flags(items):
    return [arg for item in items for arg in ("--set", item)]


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("train")
    out = cli("train", "--stage", "pretrain", *flags(settings(workdir)))
    assert out.returncode == 0, out.stderr
    return workdir, out


def test_pretrain_writes_checkpoint_weights_and_logs(pretrained):
    workdir, out = pretrained
    run = workdir / "train" / "pretrain"
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 4
    weights = load_weights(run / "weights-fp16.pt")
    assert "diffuse" in weights["branches"] and "checkpoint:" in out.stdout
    assert (run / "metrics.csv").read_text().count("\n") > 4
    assert any((run / "tensorboard").rglob("events.out.tfevents.*"))
    # off a terminal: one plain progress line per logged step (log_every=1), no bar redraws
    steps = [line for line in out.stderr.splitlines() if line.startswith("pretrain step ")]
    assert [line.split(":")[0] for line in steps] == [f"pretrain step {i}/4" for i in range(1, 5)]
    assert "d.l1=" in steps[0] and "p/s=" in steps[0]
    assert "\r" not in out.stderr + out.stdout


def test_rerun_is_a_no_op_and_more_steps_resume(pretrained):
    workdir, _ = pretrained
    checkpoint = workdir / "train" / "pretrain" / "checkpoint.pt"
    before = checkpoint.stat().st_mtime_ns
    out = cli("train", "--stage", "pretrain", *flags(settings(workdir)))
    assert out.returncode == 0, out.stderr
    assert load_checkpoint(checkpoint)["step"] == 4
    assert "pretrain: complete at step 4, nothing to train" in out.stdout and "last losses" not in out.stdout
    out = cli("train", "--stage", "pretrain", *flags(settings(workdir, steps=6)))
    assert out.returncode == 0, out.stderr
    assert "resuming pretrain" in out.stdout
    assert (out.stdout + out.stderr).count("resuming pretrain") == 1, "a note is said once, not again at the end"
    assert load_checkpoint(checkpoint)["step"] == 6 and checkpoint.stat().st_mtime_ns != before


def test_finetune_from_pretrained_weights(pretrained):
    workdir, _ = pretrained
    weights = workdir / "train" / "pretrain" / "weights-fp16.pt"
    out = cli("train", "--stage", "finetune", "--init", str(weights), *flags(settings(workdir, steps=2)))
    assert out.returncode == 0, out.stderr
    assert load_checkpoint(workdir / "train" / "finetune" / "checkpoint.pt")["step"] == 2


def test_finetune_without_weights_says_what_to_pass(tmp_path):
    cfg = load_config(None, settings(tmp_path))
    assert shipped_weights(cfg.model, tmp_path) is None
    out = cli("train", "--stage", "finetune", *flags(settings(tmp_path) + ["model.channels=6"]))
    assert out.returncode == 2
    assert "--init" in out.stderr


def test_missing_init_file_is_named(tmp_path):
    out = cli("train", "--stage", "finetune", "--init", str(tmp_path / "nope.pt"), *flags(settings(tmp_path)))
    assert out.returncode == 2
    assert "nope.pt" in out.stderr


def test_changed_architecture_is_refused_until_restart(pretrained):
    workdir, _ = pretrained
    changed = settings(workdir, steps=2) + ["model.blocks=2"]
    out = cli("train", "--stage", "pretrain", *flags(changed))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "blocks" in out.stderr
    out = cli("train", "--stage", "pretrain", "--restart", *flags(changed))
    assert out.returncode == 0, out.stderr
    assert load_checkpoint(workdir / "train" / "pretrain" / "checkpoint.pt")["model"]["blocks"] == 2


def test_eval_includes_the_trained_model(pretrained):
    workdir, _ = pretrained
    weights = workdir / "train" / "pretrain" / "weights-fp16.pt"
    out = cli(
        "eval",
        "--weights",
        str(weights),
        *flags(settings(workdir) + ["eval.split='val'", "eval.repeats=1", "eval.also_ensemble_dark=true"]),
    )
    assert out.returncode == 0, out.stderr
    table = (workdir / "eval" / "table1.csv").read_text()
    assert {"noisy", "oidn", "admc"} <= {line.split(",")[1] for line in table.splitlines()[1:]}
    assert f"**Weights:** admc: {weights}" in (workdir / "eval" / "table1.md").read_text()
    devices = json.loads((workdir / "eval" / "results.json").read_text())["devices"]
    assert "dark pass" not in devices["admc"]  # the default row runs at the frontier's settings,
    assert ", ensemble of 4, dark pass" in devices["admc-ens4+dark"]  # the costly ones in a row of their own
    assert all(d.endswith(", keeps resolved input") for name, d in devices.items() if name.startswith("admc"))


def test_eval_compares_several_checkpoints_in_one_table(pretrained):
    workdir, _ = pretrained
    run = workdir / "train" / "pretrain"
    common = flags(
        settings(workdir)
        + ["eval.split='val'", "eval.repeats=1", "eval.warmup=0", "eval.optix='off'", "eval.also_ensemble_dark=false"]
    )  # one row per checkpoint
    out = cli(
        "eval",
        "--weights",
        str(run / "weights-fp16.pt"),
        "--weights",
        f"last={run / 'checkpoint.pt'}",
        "--set",
        "eval.out_dir='eval-two'",
        *common,
    )
    assert out.returncode == 0, out.stderr
    doc = json.loads((workdir / "eval-two" / "results.json").read_text())
    assert {row["method"] for row in doc["table"]} == {"noisy", "oidn", "admc-pretrain", "last"}
    assert doc["weights"] == {"admc-pretrain": str(run / "weights-fp16.pt"), "last": str(run / "checkpoint.pt")}
    # both files hold the run's final networks (fp16 export vs fp32 checkpoint): scores agree closely. In
    # float32 the networks differ by the fp16 rounding of their weights (2^-11 relative); under bf16
    # autocast (auto on CPUs with AVX512-BF16) both are rounded to bf16 before use and differ less still
    scores = {(r["scene_id"], r["spp"], r["method"]): r["relmse"] for r in doc["images"]}
    for scene, spp, method in scores:
        if method == "last":
            assert scores[(scene, spp, "last")] == pytest.approx(scores[(scene, spp, "admc-pretrain")], rel=0.05)
    clash = cli("eval", "--weights", str(run / "weights-fp16.pt"), "--weights", str(run / "checkpoint.pt"), *common)
    assert clash.returncode == 2 and "name them apart with NAME=PATH" in clash.stderr
    both = cli("eval", "--no-model", "--weights", str(run / "checkpoint.pt"), *common)
    assert both.returncode == 2 and "contradict" in both.stderr


def test_ship_weights_publishes_the_run_or_a_checkpoint_saved_at_a_chosen_step(pretrained, tmp_path):
    workdir, _ = pretrained
    run = workdir / "train" / "pretrain"
    saved = tmp_path / "saved.pt"  # what a user copies aside at the step an out-of-family score picks
    saved.write_bytes((run / "checkpoint.pt").read_bytes())
    ship = [sys.executable, str(SHIP_WEIGHTS), str(run), "--to", str(tmp_path / "weights")]
    out = subprocess.run([*ship, "from-run", "--note", "the run's own pick"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "weights" / "from-run.pt").read_bytes() == (run / "weights-fp16.pt").read_bytes()
    out = subprocess.run([*ship, "chosen", "--checkpoint", str(saved)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    checkpoint, shipped = load_checkpoint(saved), load_weights(tmp_path / "weights" / "chosen.pt")
    step = checkpoint["step"]
    assert shipped["metadata"]["step"] == step and shipped["metadata"]["model"] == checkpoint["model"]
    assert {b: s["step"] for b, s in shipped["metadata"]["selected"].items()} == {"diffuse": step, "specular": step}
    for branch, state in checkpoint["branches"].items():  # fp16 of exactly the checkpoint's networks
        generator = state.get("average", state["generator"])
        assert all(torch.equal(shipped["branches"][branch]["generator"][k], v.half()) for k, v in generator.items())
    entries = json.loads((tmp_path / "weights" / "manifest.json").read_text())["weights"]
    assert [(e["file"], e["steps"]) for e in entries] == [("chosen.pt", step)]  # same architecture: replaced
    start = tmp_path / "weights" / "from-run.pt"
    out = subprocess.run(
        [*ship, "blend", "--checkpoint", str(saved), "--blend-from", str(start), "--blend", "0.25"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    blend, begin = load_weights(tmp_path / "weights" / "blend.pt"), load_weights(start)
    for branch, state in checkpoint["branches"].items():  # 0.75 x the start + 0.25 x the checkpoint, then fp16
        for key, value in state.get("average", state["generator"]).items():
            expected = (0.75 * begin["branches"][branch]["generator"][key].float() + 0.25 * value.float()).half()
            assert torch.equal(blend["branches"][branch]["generator"][key], expected)
    assert blend["metadata"]["selected"]["diffuse"]["blend"] == 0.25
    other = WEIGHTS_DIR / "admc-small-pretrained.pt"  # another architecture: refused, named
    out = subprocess.run(
        [*ship, "mixed", "--checkpoint", str(saved), "--blend-from", str(other)], capture_output=True, text=True
    )
    assert out.returncode != 0 and f"{other}: not the architecture" in out.stderr
    assert not (tmp_path / "weights" / "mixed.pt").exists()
    out = subprocess.run(
        [*ship, "far", "--checkpoint", str(saved), "--blend-from", str(start), "--blend", "1.5"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 2 and "--blend 1.5" in out.stderr and "Traceback" not in out.stderr


def test_denoise_a_rendered_exr_and_an_oidn_style_set(pretrained, tmp_path):
    import numpy as np
    from admc.common.buffers import BEAUTY
    from admc.stores.exr import read_exr, write_exr

    workdir, _ = pretrained
    weights = workdir / "train" / "pretrain" / "weights-fp16.pt"
    render = next((workdir / "renders").iterdir()) / "spp0002.exr"
    out = cli("denoise", str(render), "-o", str(tmp_path / "a.exr"), "--weights", str(weights))
    assert out.returncode == 0, out.stderr
    layers = read_exr(tmp_path / "a.exr")
    assert layers[BEAUTY].shape == (64, 64, 3) and np.isfinite(layers[BEAUTY]).all()
    assert "dark pass" not in out.stdout  # off unless asked for
    out = cli("denoise", str(render), "-o", str(tmp_path / "b.exr"), "--weights", str(weights), "--dark-pass")
    assert out.returncode == 0 and ", dark pass, keeps resolved input)" in out.stdout, out.stderr
    assert np.isfinite(read_exr(tmp_path / "b.exr")[BEAUTY]).all()

    src = read_exr(render)
    colour = src["diffuse"] + src.get("specular", 0)
    for suffix, name, data in (
        (".hdr.exr", "diffuse", colour),
        (".alb.exr", "albedo", src["albedo"]),
        (".nrm.exr", "normal", src["normal"]),
    ):
        write_exr(tmp_path / f"shot{suffix}", {BEAUTY: data}, precision="float")
    out = cli("denoise", str(tmp_path / "shot.hdr.exr"), "--weights", str(weights))
    assert out.returncode == 0, out.stderr
    assert "diffuse only" in out.stdout  # a combined colour cannot be split: it says so
    assert read_exr(tmp_path / "shot.denoised.exr")[BEAUTY].shape == (64, 64, 3)


def test_the_default_config_finds_the_shipped_weights_and_they_load():
    """`make demo` fine-tunes from weights/: the default [model] must match a manifest entry (settings
    added after the weights were shipped take the defaults that reproduce them)."""
    from admc.model.inference.denoiser import load_denoiser

    model = load_config().model
    path = shipped_weights(model)
    assert path is not None and path.is_file()
    denoiser = load_denoiser(path)
    assert set(denoiser.generators) == {"diffuse", "specular"}


def test_finetune_names_how_the_config_differs_from_the_shipped_weights(tmp_path):
    """A [model] the shipped weights do not have: the message names each differing key and its shipped value."""
    out = cli(
        "train",
        "--stage",
        "finetune",
        "--set",
        "model.backbone=unet",
        "--set",
        "model.channels=24",
        "--set",
        f"run.workdir='{tmp_path}'",
    )
    assert out.returncode == 2
    assert "admc-small-pretrained.pt has model.backbone = 'residual', model.channels = 16" in out.stderr, out.stderr
    assert "admc-small-refiner.pt" not in out.stderr and "Traceback" not in out.stderr


def test_every_shipped_file_is_whole_and_is_the_architecture_its_entry_names():
    """weights/manifest.json is what fine-tuning and evaluation trust: each file hashes to its entry and loads
    as the [model] the entry records (the multi-scale admc-small-unet.pt beside the residual files)."""
    import hashlib

    from admc.model.inference.denoiser import load_denoiser
    from admc.model.nets.settings import ModelSettings
    from admc.model.nets.unet import UNetGenerator
    from admc.pipeline.weights import WEIGHTS_DIR

    entries = json.loads((WEIGHTS_DIR / "manifest.json").read_text())["weights"]
    assert {e["model"]["backbone"] for e in entries} == {"residual", "unet"}
    for entry in entries:
        path = WEIGHTS_DIR / entry["file"]
        assert hashlib.sha256(path.read_bytes()).hexdigest() == entry["sha256"], entry["file"]
        model = ModelSettings.from_saved(entry["model"])
        assert shipped_weights(model) == path
        generator = load_denoiser(path).generators["diffuse"]
        assert isinstance(generator, UNetGenerator) == (model.backbone == "unet"), entry["file"]


def test_finetune_and_eval_with_the_noise_input(pretrained):
    """`train --stage finetune --set model.noise_input=true`: the store gains noise maps (re-tiled from the
    cached renders), the run lives beside the others (finetune-noise) and eval finds and runs it."""
    workdir, _ = pretrained
    weights = workdir / "train" / "pretrain" / "weights-fp16.pt"
    blocks = load_weights(weights)["metadata"]["model"]["blocks"]  # an earlier test may have changed it
    noise = settings(workdir, steps=2) + [f"model.blocks={blocks}", "model.noise_input=true"]
    out = cli("train", "--stage", "finetune", "--init", str(weights), *flags(noise))
    assert out.returncode == 0, out.stderr
    assert "the noise input added, its weights starting at 0" in out.stdout + out.stderr
    checkpoint = load_checkpoint(workdir / "train" / "finetune-noise" / "checkpoint.pt")
    assert checkpoint["step"] == 2 and checkpoint["model"]["noise_input"] is True
    out = cli(
        "eval",
        *flags(noise + ["eval.split='val'", "eval.repeats=1", "eval.also_ensemble_dark=false", "eval.engine='torch'"]),
    )
    assert out.returncode == 0, out.stderr
    assert (
        f"admc: {workdir / 'train' / 'finetune-noise' / 'weights-fp16.pt'}"
        in (workdir / "eval" / "table1.md").read_text()
    )


def test_a_noise_input_model_without_weights_of_its_own_starts_from_those_without_it(tmp_path):
    import dataclasses

    plain = load_config().model
    noise = dataclasses.replace(plain, noise_input=True)
    entries = [{"file": "plain.pt", "model": dataclasses.asdict(plain)}]
    (tmp_path / "manifest.json").write_text(json.dumps({"weights": entries}))
    assert shipped_weights(noise, tmp_path) == tmp_path / "plain.pt"  # fine-tuning adds the input (load_init)
    assert shipped_weights(dataclasses.replace(noise, channels=24), tmp_path) is None
    entries.append({"file": "noise.pt", "model": dataclasses.asdict(noise)})
    (tmp_path / "manifest.json").write_text(json.dumps({"weights": entries}))
    assert shipped_weights(noise, tmp_path) == tmp_path / "noise.pt"
    assert shipped_weights(plain, tmp_path) == tmp_path / "plain.pt"  # an input is never dropped
