"""Data-parallel training with 2 real gloo processes on the CPU (tiny networks, a tiny real store):
2 ranks take the single-process steps at the same global batch, and a killed rank ends the run with one
clear message and a checkpoint that resumes."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest
import torch

from conftest import build_tiny_store, tiny_store_overrides
from rank_helpers import outlive_a_peer
from admc.errors import TrainingError
from admc.model.nets.settings import ModelSettings
from admc.model.training import distributed
from admc.model.train_settings import TrainSettings
from admc.model.training.trainer import train
from admc.pipeline.config import load_config
from admc.pipeline.stages.train import run_training
from admc.pipeline.weights import train_dir
from admc.stores.checkpoints import load_checkpoint

ADMC = str(Path(sys.executable).parent / "admc-pipe")
CPU = torch.device("cpu")
TINY = ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16, critic_channels=4)
# One step of each phase (L1, critic alone, adversarial), validated before and after, global batch 4.
SETTINGS = TrainSettings(
    steps=3,
    batch_size=4,
    l1_warmup_steps=1,
    critic_only_steps=1,
    critic_steps_per_g=1,
    lr_g_diffuse=1e-4,
    lr_g_specular=1e-4,
    lr_d=1e-4,
    head_tail_start_step=0,
    lr_milestones=(5,),
    val_every=3,
    val_patches=4,
    checkpoint_every=3,
    log_every=1,
    num_workers=0,
    threads=1,
    device="cpu",
    precision="float32",
    seed=1,
    max_bad_steps=3,
)
# The two runs compute the same sums in another order: each rank sums its half of the batch, then the
# halves are averaged. A weight gradient here sums n = 2 x 32 x 32 = 2048 per-pixel products per rank,
# whose float32 rounding is at most n * 2^-24 = 1.2e-4 of the magnitudes summed (Higham's bound);
# measured: < 1e-5 of each tensor's largest entry. A rank that used its own half's gradient instead of
# the mean would differ by O(1).
GRAD_RTOL = 2048 * 2.0**-24


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, variant):
    """(workdir, patch store) of a 4-scene corpus."""
    workdir = tmp_path_factory.mktemp("ddp")
    return workdir, build_tiny_store(workdir, size=64, patch=32)


def assert_moments_close(single, ranks, where):
    """Adam's moments hold the (averaged) gradients of every step: equal up to the rounding above."""
    for name, opt in single["optimizers"].items():
        for pid, state in opt["state"].items():
            for key in ("exp_avg", "exp_avg_sq"):
                a, b = state[key], ranks["optimizers"][name]["state"][pid][key]
                assert (a - b).abs().max() <= GRAD_RTOL * a.abs().max(), (where, name, pid, key)


def test_two_ranks_take_the_single_process_steps(tiny, tmp_path):
    store = tiny[1]
    single = train(store, tmp_path / "single", SETTINGS, TINY, progress=False)
    kwargs = dict(store_path=store, out_dir=tmp_path / "ranks", settings=SETTINGS, model=TINY, progress=False)
    ranks = distributed.launch(2, CPU, train, kwargs)
    a, b = load_checkpoint(single.checkpoint), load_checkpoint(ranks.checkpoint)
    assert a["step"] == b["step"] == 3
    for branch in a["branches"]:
        sa, sb = a["branches"][branch], b["branches"][branch]
        assert sa["batches"] == sb["batches"]  # the same global batches consumed: resume continues alike
        assert_moments_close(sa, sb, branch)
        for net in ("generator", "critic"):
            for key, w in sa[net].items():
                # Adam moves a weight by at most ~lr per step, even where rounding flips the sign of a
                # near-zero gradient: body weights learn at body_lr_factor x lr.
                bound = 2 * SETTINGS.steps * SETTINGS.body_lr_factor * 1e-4
                assert (w.float() - sb[net][key].float()).abs().max() <= bound, (branch, net, key)
    # The penalty's mixing weights came from the same draws: the RNG ended in the same state.
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])
    # Rank 0 validated the same networks on the same patches and shipped the same steps.
    assert {k: v["step"] for k, v in single.selected.items()} == {k: v["step"] for k, v in ranks.selected.items()}
    for branch, values in single.validation.items():
        assert ranks.validation[branch]["relmse"] == pytest.approx(values["relmse"], rel=GRAD_RTOL)
    assert ranks.rank == 0 and ranks.weights.is_file()


@pytest.mark.parametrize(
    "setting, message",
    [
        ("train.batch_size=3", r"'train.batch_size'.*3 does not split across 2 training processes"),
        ("model.critic_norm=batch", r"'model.critic_norm'.*each of the 2 training processes' slices"),
    ],
)
def test_what_does_not_split_is_refused_before_anything_runs(tiny, setting, message):
    cfg = load_config(None, [*cli_settings(tiny[0], steps=2), setting])
    with pytest.raises(TrainingError, match=message):
        run_training(cfg, "pretrain", progress=False, nproc=2)
    assert not train_dir(cfg, "pretrain").exists()


def test_a_rank_that_loses_its_peer_says_so():
    message = distributed.launch(2, CPU, outlive_a_peer, {})
    assert message.startswith("training process rank 0 of 2 lost contact with the others ("), message


def cli_settings(workdir, steps):
    return [
        *tiny_store_overrides(workdir, 64, 32),
        "model.channels=8",
        "model.blocks=1",
        "model.cond_channels=8",
        "model.encoder_channels=8",
        "model.critic_channels=4",
        f"train.steps={steps}",
        "train.batch_size=2",
        "train.l1_warmup_steps=1",
        "train.critic_only_steps=1",
        "train.head_tail_start_step=0",
        "train.val_every=0",
        "train.checkpoint_every=2",
        "train.log_every=1",
        "train.threads=1",
        "train.device=cpu",
        "train.precision=float32",
    ]


def rank_processes(parent: psutil.Process) -> list[psutil.Process]:
    return [p for p in parent.children() if "spawn_main" in " ".join(p.cmdline())]


def test_a_killed_rank_ends_the_run_clearly_and_its_checkpoint_resumes(tiny):
    workdir = tiny[0]
    items = cli_settings(workdir, steps=100_000)
    checkpoint = train_dir(load_config(None, items), "pretrain") / "checkpoint.pt"
    command = [ADMC, "train", "--nproc", "2", *[a for item in items for a in ("--set", item)]]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not checkpoint.is_file() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert checkpoint.is_file(), proc.stderr.read() if proc.poll() is not None else "no checkpoint in 120 s"
        victim = max(rank_processes(psutil.Process(proc.pid)), key=lambda p: p.pid)  # rank 1, started last
        os.kill(victim.pid, signal.SIGKILL)
        out, err = proc.communicate(timeout=60)  # no hang: the parent sees the death at once
    finally:
        proc.kill()
    assert proc.returncode == 2, err
    assert "Traceback" not in err and "\nerror: training process rank" in err, err
    assert "run the same command to resume" in err, err
    progress = [line for line in err.splitlines() if line.startswith("pretrain step 2/")]
    assert len(progress) == 1, err  # rank 0 alone speaks
    # The checkpoint it left resumes (here in one process at the same global batch) and trains on.
    saved = load_checkpoint(checkpoint)["step"]
    cfg = load_config(None, cli_settings(workdir, steps=saved + 2))
    result = run_training(cfg, "pretrain", progress=False)
    assert result.step == saved + 2 and any(f"at step {saved}" in note for note in result.notes)
