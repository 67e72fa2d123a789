"""The trainer on a real tiny patch store (32x32 patches, tiny networks, CPU): the step overfits,
stop + resume equals an uninterrupted run bit for bit, non-finite data never reaches the weights,
bad stores are refused, every ablation trains, and checkpoints/weights round-trip."""

import dataclasses
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr
from zarr.storage import LocalStore

from conftest import build_tiny_store, preset
from admc.model.nets.settings import MODES, ModelSettings
from admc.model.training.branch import BranchTrainer
from admc.model.training.data import load_rows
from admc.model.train_settings import TrainSettings
from admc.errors import TrainingError
from admc.model.training.trainer import TrainingDiverged, train
from admc.stores.checkpoints import (
    CheckpointError,
    export_weights,
    load_checkpoint,
    load_weights,
    read_networks,
    save_checkpoint,
)
from admc.stores.patches import PatchReader, PatchStoreError

TINY = ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16, critic_channels=4)
SETTINGS = TrainSettings(
    steps=7,
    batch_size=2,
    l1_warmup_steps=2,
    critic_only_steps=1,
    critic_steps_per_g=2,
    lr_g_diffuse=1e-4,
    lr_g_specular=1e-4,
    lr_d=1e-4,
    head_tail_start_step=3,
    lr_milestones=(5,),
    val_every=3,
    val_patches=4,
    checkpoint_every=2,
    log_every=2,
    num_workers=0,
    threads=0,
    device="cpu",
    precision="float32",
    seed=1,
    max_bad_steps=3,
)
PRECISIONS = ("float32", "bfloat16")


@pytest.fixture(scope="module")
def store(tmp_path_factory, variant):
    tmp = tmp_path_factory.mktemp("train_store")
    path = build_tiny_store(tmp, size=64, patch=32)
    assert len(PatchReader(path, "train", branch="specular")) > 0  # both branches get trained below
    return path


@pytest.fixture
def store_copy(store, tmp_path):
    copy = tmp_path / "copy.zarr"
    shutil.copytree(store, copy)
    return copy


def flat_state(obj, prefix=""):
    """Every tensor and number in a nested state, keyed by path."""
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            out.update(flat_state(v, f"{prefix}/{k}"))
        return out
    if isinstance(obj, (list, tuple)):
        out = {}
        for i, v in enumerate(obj):
            out.update(flat_state(v, f"{prefix}/{i}"))
        return out
    return {prefix: obj}


def assert_states_equal(a, b):
    fa, fb = flat_state(a), flat_state(b)
    assert fa.keys() == fb.keys()
    for key in fa:
        if isinstance(fa[key], torch.Tensor):
            assert torch.equal(fa[key], fb[key]), key
        else:
            assert fa[key] == fb[key], key


def batch_of(store, n=4, split="train"):
    return load_rows(PatchReader(store, split), n)


def snapshot(module):
    return {k: v.clone() for k, v in module.state_dict().items()}


def test_the_step_overfits_a_handful_of_patches(store):
    torch.manual_seed(0)
    settings = dataclasses.replace(SETTINGS, adversarial=False, lr_g_diffuse=2e-3, head_tail_start_step=0)
    trainer = BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
    batch = batch_of(store)
    noisy_l1 = float((batch["noisy"] - batch["reference"]).abs().mean())
    losses = [trainer.step(i, [batch])[1]["l1"] for i in range(150)]
    # Measured: 0.154 -> 0.042, while the noisy input itself is 0.083 from the reference: the tiny
    # generator falls by > 3.5x and ends at half the input's error (margins for other torch builds).
    assert losses[-1] < losses[0] / 2.5, (losses[0], losses[-1])
    assert losses[-1] < 0.75 * noisy_l1, (noisy_l1, losses[-1])
    assert trainer.bad_total == 0


@pytest.mark.parametrize("mode", MODES)
def test_every_ablation_builds_and_takes_an_adversarial_step(store, mode):
    torch.manual_seed(0)
    model = dataclasses.replace(TINY, mode=mode)
    settings = dataclasses.replace(
        SETTINGS, l1_warmup_steps=0, critic_only_steps=0, critic_steps_per_g=1, head_tail_start_step=0
    )
    trainer = BranchTrainer("diffuse", model, settings, 32, torch.device("cpu"))
    g0, d0 = snapshot(trainer.generator), snapshot(trainer.critic)
    ok, losses = trainer.step(0, [batch_of(store)])
    assert ok and {"l1", "adversarial", "wasserstein", "gp"} <= losses.keys()
    assert not torch.equal(trainer.generator.head.weight, g0["head.weight"])
    assert any(not torch.equal(v, d0[k]) for k, v in trainer.critic.state_dict().items())


def test_l1_only_ablation_never_touches_the_critic(store):
    torch.manual_seed(0)
    settings = dataclasses.replace(SETTINGS, adversarial=False)
    trainer = BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
    d0 = snapshot(trainer.critic)
    for step in range(5):  # would be critic-only and adversarial steps with adversarial=True
        ok, losses = trainer.step(step, [batch_of(store)])
        assert ok and "adversarial" not in losses and "wasserstein" not in losses
    assert_states_equal(trainer.critic.state_dict(), d0)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("poison", ["nan_input", "overflowing_input"])
def test_a_non_finite_batch_never_reaches_the_weights(store, poison, precision):
    torch.manual_seed(0)
    settings = dataclasses.replace(
        SETTINGS,
        l1_warmup_steps=0,
        critic_only_steps=0,
        critic_steps_per_g=1,
        head_tail_start_step=0,
        precision=precision,
    )
    trainer = BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
    assert trainer.step(0, [batch_of(store)])[0]
    before = {
        "g": snapshot(trainer.generator),
        "d": snapshot(trainer.critic),
        "opt": {k: o.state_dict() for k, o in trainer.optimizers.items()},
        "sched": {k: s.state_dict() for k, s in trainer.schedulers.items()},
    }
    bad = batch_of(store)
    if poison == "nan_input":
        bad["noisy"][1, 0, 3, 3] = float("nan")
    else:  # finite, but the forward pass overflows float32: caught by the loss guard
        bad["noisy"] = bad["noisy"] * 3e38
    ok, _ = trainer.step(1, [bad])
    assert not ok
    assert (trainer.bad_total, trainer.bad_consecutive) == (1, 1)
    after = {
        "g": trainer.generator.state_dict(),
        "d": trainer.critic.state_dict(),
        "opt": {k: o.state_dict() for k, o in trainer.optimizers.items()},
        "sched": {k: s.state_dict() for k, s in trainer.schedulers.items()},
    }
    assert_states_equal(before, after)
    assert trainer.step(2, [batch_of(store)])[0]
    assert (trainer.bad_total, trainer.bad_consecutive) == (1, 0)


@pytest.mark.parametrize("precision", PRECISIONS)
def test_stop_and_resume_equals_one_uninterrupted_run(store, tmp_path, precision):
    settings = dataclasses.replace(SETTINGS, precision=precision)
    whole = train(store, tmp_path / "whole", settings, TINY, progress=False)
    first = train(store, tmp_path / "split", dataclasses.replace(settings, steps=4), TINY, progress=False)
    assert first.step == 4 and load_checkpoint(first.checkpoint)["step"] == 4
    second = train(store, tmp_path / "split", settings, TINY, resume=True, progress=False)
    assert second.step == 7 and whole.branches == second.branches == ["diffuse", "specular"]
    a, b = load_checkpoint(whole.checkpoint), load_checkpoint(second.checkpoint)
    assert_states_equal(a["branches"], b["branches"])  # weights, Adam moments, schedulers, stream positions
    assert a["branches"]["diffuse"]["batches"] == 2 + 1 + 4 * 2  # l1, critic-only, 4 adversarial x 2 batches
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])
    # the trained weights moved away from the initial ones, and validation and logs were written
    assert whole.validation["diffuse"]["relmse"] > 0 and np.isfinite(whole.validation["specular"]["psnr"])
    csv_text = (tmp_path / "split" / "metrics.csv").read_text()
    assert "diffuse/val_psnr" in csv_text and "specular/wasserstein" in csv_text
    assert csv_text.count("\n6,diffuse/l1,") == 1  # resumed logs are not duplicated
    assert list((tmp_path / "whole" / "tensorboard").glob("events.out.tfevents.*"))
    assert a["precision"] == b["precision"] == precision


def test_a_spent_time_budget_ends_the_run_validated_and_a_larger_one_resumes_it(store, tmp_path):
    out = tmp_path / "budget"
    tiny_budget = dataclasses.replace(SETTINGS, minutes=1e-6)  # spent before the first step ends
    first = train(store, out, tiny_budget, TINY, progress=False)
    saved = load_checkpoint(first.checkpoint)
    assert first.step == saved["step"] == 1 and saved["seconds"] > 0
    assert any("train.minutes" in note and "step 1 of 7" in note for note in first.notes), first.notes
    assert first.validation["diffuse"]["relmse"] > 0 and first.weights.is_file()  # validated and shipped at its end
    again = train(store, out, tiny_budget, TINY, resume=True, progress=False)
    assert again.step == 1 and not again.last_losses  # the budget stays spent across the resume: nothing to train
    rest = train(store, out, dataclasses.replace(SETTINGS, minutes=0.0), TINY, resume=True, progress=False)
    assert rest.step == 7 and load_checkpoint(rest.checkpoint)["seconds"] > saved["seconds"]


def test_validation_shows_each_branch_against_its_start_and_oidn_on_the_same_patches(store, tmp_path, capsys):
    settings = dataclasses.replace(SETTINGS, steps=3, val_every=3)
    result = train(store, tmp_path / "shown", settings, TINY, progress=True)
    lines = [line for line in capsys.readouterr().err.splitlines() if " validation: " in line]
    assert [line.split(" validation")[0] for line in lines] == [
        "step 0 diffuse",
        "step 0 specular",
        "step 3 diffuse",
        "step 3 specular",
    ]
    assert all("x the start" in line and "x OIDN" in line for line in lines), lines
    for branch, val in result.validation.items():  # the store's OIDN rows of the same patches, as ratios
        assert val["relmse_vs_oidn"] == pytest.approx(val["relmse"] / val["oidn_relmse"])
        assert val["oidn_relmse"] < val["noisy_relmse"]
        assert f"{val['relmse_vs_oidn']:.3f}x OIDN" in lines[2 if branch == "diffuse" else 3]


def test_best_blend_finds_the_share_that_halves_two_independent_errors():
    """Two estimates with independent errors of equal size: their even blend has about half the squared
    error of either, and best_blend finds a share near 0.5; an exact estimate keeps its whole share."""
    from admc.model.training.validation import best_blend, to_linear

    torch.manual_seed(0)
    features = torch.rand(64, 7, 16, 16)
    reference = torch.rand(64, 3, 16, 16) + 0.5
    ref_linear = to_linear(reference, features, "specular")
    errors = [0.05 * torch.randn(64, 3, 16, 16, dtype=torch.float64) for _ in range(2)]
    val = {"reference": reference, "features": features, "oidn": torch.log1p(ref_linear + errors[1]).float()}
    share, blended = best_blend(ref_linear + errors[0], val, "specular")
    alone = float(((errors[0] ** 2) / (ref_linear**2 + 0.01)).mean())
    assert 0.4 <= share <= 0.6 and blended < 0.6 * alone
    assert best_blend(ref_linear, val, "specular")[0] == 1.0


def test_an_oidn_blend_is_chosen_on_validation_and_shipped_with_the_weights(store, tmp_path, capsys):
    from admc.model.inference.denoiser import load_denoiser
    from admc.stores.checkpoints import read_blend

    settings = dataclasses.replace(SETTINGS, steps=3, val_every=3, oidn_blend=True)
    result = train(store, tmp_path / "blend", settings, TINY, progress=True)
    shipped = read_blend(result.weights)
    assert set(shipped) == {"diffuse", "specular"}
    for branch, share in shipped.items():  # the share of the step the weights hold, as validation showed it
        assert share == result.validation[branch]["blend_share"] or result.selected[branch]["step"] == 0
        assert 0.0 <= share <= 1.0 and any(f"ships blended with OIDN, {share:.2f}" in n for n in result.notes)
    assert "with OIDN, relMSE" in capsys.readouterr().err
    assert load_denoiser(result.weights).oidn_blend == shipped
    assert load_denoiser(result.weights, oidn_blend=False).oidn_blend == {}
    assert read_blend(result.checkpoint) == {}  # a checkpoint carries no blend: its weights file ships it


def test_a_fine_tuned_oidn_partner_is_trained_first_selected_on_validation_and_shipped(store, tmp_path, capsys):
    """train.oidn_minutes: OIDN's networks train before admc's steps, start as the library's weights (step 0's
    validation), keep their best validated step, ride in the weights file, and the denoiser blends with them."""
    from admc.model.inference.denoiser import load_denoiser
    from admc.model.nets.oidn_unet import oidn_unet
    from admc.stores.checkpoints import read_blend, read_oidn_networks

    settings = dataclasses.replace(SETTINGS, steps=2, val_every=2, oidn_blend=True, oidn_minutes=0.02)
    result = train(store, tmp_path / "partner", settings, TINY, progress=True)
    err = capsys.readouterr().err
    assert "OIDN fine-tune step 0 diffuse" in err and "with fine-tuned OIDN, relMSE" in err
    shipped = read_oidn_networks(result.weights)
    assert set(shipped) == {"diffuse", "specular"}
    for branch, state in shipped.items():
        assert state["enc_conv0.weight"].dtype == torch.float16
        note = next(n for n in result.notes if n.startswith(f"{branch}: OIDN's network ships"))
        library = oidn_unet(branch).state_dict()
        if "ships its own weights: no step of its fine-tune" in note:  # none beat them on the val rows
            assert all(torch.equal(state[k], v.half()) for k, v in library.items())
        else:
            assert any(not torch.equal(state[k], v.half()) for k, v in library.items())
    denoiser = load_denoiser(result.weights)
    assert denoiser.oidn_blend == read_blend(result.weights) and set(denoiser.oidn_partner) == set(shipped)
    assert "OIDN fine-tuned with it" in denoiser.device


def test_a_large_oidn_partner_starts_from_oidns_final_frame_route_and_ships_large(store, tmp_path, capsys):
    """train.oidn_network = "large": the diffuse partner is OIDN's large network on prefiltered guides (its step 0
    scores the library's final-frame route on the val rows), the specular one stays standard (OIDN has no large
    colour-only network); the weights ship each at its size and the denoiser runs them."""
    from admc.model.inference.denoiser import load_denoiser
    from admc.model.training.oidn_partner import METRIC_LABELS, start_partner
    from admc.stores.checkpoints import read_oidn_networks
    from admc.stores.exr import read_exr

    settings = dataclasses.replace(
        SETTINGS, steps=1, val_every=1, oidn_blend=True, oidn_minutes=0.02, oidn_network="large", oidn_select="relmse"
    )
    result = train(store, tmp_path / "large", settings, TINY, progress=True)
    assert "OIDN fine-tune step 0 diffuse: val " + METRIC_LABELS["relmse"] in capsys.readouterr().err
    shipped = read_oidn_networks(result.weights)
    assert "enc_conv1a.weight" in shipped["diffuse"] and "enc_conv0.weight" in shipped["specular"]
    denoiser = load_denoiser(result.weights)
    image = denoiser(read_exr(next(Path(store).parent.glob("renders/*/spp0004.exr"))))
    assert np.isfinite(image.diffuse).all() and (image.diffuse >= 0).all()
    partner = start_partner(["diffuse", "specular"], settings, None, torch.device("cpu"))
    rates = {name: opt.param_groups[0]["lr"] for name, opt in partner.optimizers.items()}
    assert (
        rates == {"diffuse": settings.oidn_lr_large, "specular": settings.oidn_lr}
        and rates["diffuse"] < settings.oidn_lr
    )
    with pytest.raises(ValueError, match="^oidn_network: 'huge' is not one of"):
        TrainSettings(oidn_network="huge").check()


def test_a_large_partner_trains_on_rows_whose_guides_oidn_prefiltered_once(store):
    """PrefilteredGuides: each row's albedo and normal (stored as (n + 1) / 2) are OIDN's prefiltered ones, the
    rest of the row as stored; a row is prefiltered once."""
    from admc.common import oidn
    from admc.common.layout import ALBEDO, NORMAL
    from admc.model.training.oidn_partner import PrefilteredGuides

    reader = PatchReader(store, "train", branch="diffuse")
    rows = PrefilteredGuides(reader)
    stored, item = reader[1], rows[1]
    albedo = oidn.prefilter("albedo", stored["features"][ALBEDO].transpose(1, 2, 0))
    normal = oidn.prefilter("normal", stored["features"][NORMAL].transpose(1, 2, 0) * 2 - 1)
    assert np.array_equal(item["features"][ALBEDO], albedo.transpose(2, 0, 1))
    assert np.allclose(item["features"][NORMAL], normal.transpose(2, 0, 1) * 0.5 + 0.5, atol=1e-7)
    assert not np.array_equal(item["features"][ALBEDO], stored["features"][ALBEDO])
    others = [c for c in range(stored["features"].shape[0]) if c not in range(4, 7) and c not in range(3)]
    assert np.array_equal(item["features"][others], stored["features"][others])
    assert np.array_equal(item["noisy"], stored["noisy"]) and len(rows) == len(reader)
    first = rows.guides[1]
    rows[1]
    assert rows.guides[1] is first and list(rows.guides) == [1]


def test_a_resumed_run_keeps_its_fine_tuned_oidn_partner(store, tmp_path):
    """The partner's state rides in the checkpoint: a resumed run does not train OIDN again and ships the
    same networks."""
    from admc.stores.checkpoints import read_oidn_networks

    settings = dataclasses.replace(SETTINGS, steps=2, val_every=2, oidn_blend=True, oidn_minutes=0.02)
    first = train(store, tmp_path / "run", settings, TINY, progress=False)
    shipped = read_oidn_networks(first.weights)
    assert read_oidn_networks(first.checkpoint).keys() == shipped.keys()
    second = train(store, tmp_path / "run", dataclasses.replace(settings, steps=4), TINY, resume=True, progress=False)
    assert second.step == 4 and not any("fine-tuning OIDN's networks first" in n for n in second.notes)
    again = read_oidn_networks(second.weights)
    assert all(torch.equal(shipped[b][k], again[b][k]) for b in shipped for k in shipped[b])


def test_the_oidn_partner_on_a_clean_target_store_learns_raw_diffuse_and_tries_both_speculars(
    tmp_path_factory, variant, capsys
):
    """A store tiled with tile.clean_targets keeps the raw references too: OIDN's diffuse network learns from them
    (oidn_partner.CANDIDATES); the specular one trains on both targets from the same batches until the first
    validation, where the one with the lower val relMSE (train.oidn_select = "relmse") goes on alone; a
    checkpoint written after that resumes with the networks it holds. It trains with OIDN's own loss
    (train.oidn_loss), the other partner tests with L1."""
    from admc.common.layout import RAW
    from admc.model.training.oidn_partner import start_partner

    tmp = tmp_path_factory.mktemp("clean_store")
    store = build_tiny_store(tmp, size=64, patch=32, extra=["tile.clean_targets=true"])
    settings = dataclasses.replace(
        SETTINGS, steps=1, val_every=2, oidn_blend=True, oidn_minutes=0.03, oidn_loss="l1_msssim", oidn_select="relmse"
    )
    result = train(store, tmp / "run", settings, TINY, progress=True)
    err = capsys.readouterr().err
    partner = load_checkpoint(result.checkpoint)["partner"]
    assert "diffuse" not in partner["scores"] and "OIDN fine-tune step 0 diffuse, raw targets" in err
    assert any(n.startswith("diffuse: OIDN's network ships") and "on the raw references" in n for n in result.notes)
    assert "OIDN fine-tune step 2 specular, raw targets: val relMSE" in err
    kept = [name for name in partner["nets"] if name.startswith("specular")]
    mine, raw = partner["scores"]["specular"][2]["relmse"], partner["scores"]["specular" + RAW][2]["relmse"]
    assert kept == ["specular" + RAW if raw < mine else "specular"]  # the trial is over: one goes on
    dropped = "specular" if raw < mine else "specular" + RAW
    assert max(partner["scores"][dropped]) == 2  # the other one trained no further
    targets = "raw" if raw < mine else "cleaned"
    assert f"OIDN fine-tune specular: goes on with the {targets} targets" in err
    assert any(n.startswith("specular: OIDN's network ships") and f"on the {targets} " in n for n in result.notes)
    assert set(partner["nets"]) == {"diffuse" + RAW, *kept}
    resumed = start_partner(["diffuse", "specular"], settings, None, torch.device("cpu"), ["diffuse", "specular"])
    resumed.load_state_dict(partner)
    assert set(resumed.nets) == set(partner["nets"]) == set(resumed.optimizers)


def test_the_oidn_partner_can_rank_its_steps_by_relmse_and_hdr_flip_together(store, tmp_path, capsys):
    """train.oidn_select = "relmse+flip": each validation also scores HDR-FLIP, and the shipped step is the one
    with the lowest geometric mean of the two metrics' ratios to step 0 (OIDN's own weights)."""
    settings = dataclasses.replace(
        SETTINGS, steps=1, val_every=1, oidn_blend=True, oidn_minutes=0.03, oidn_select="relmse+flip"
    )
    result = train(store, tmp_path / "run", settings, TINY, progress=True)
    assert "OIDN fine-tune step 0 diffuse: val relMSE" in capsys.readouterr().err
    partner = load_checkpoint(result.checkpoint)["partner"]
    for branch, steps in partner["scores"].items():
        assert len(steps) >= 2 and all(set(s) == {"relmse", "hdr_flip"} for s in steps.values())
        start = steps[0]
        error = {
            step: ((s["relmse"] / start["relmse"]) * (s["hdr_flip"] / start["hdr_flip"])) ** 0.5
            for step, s in steps.items()
        }
        assert error[partner["best_step"][branch]] == min(error.values())
        note = next(n for n in result.notes if n.startswith(f"{branch}: OIDN's network ships"))
        assert "HDR-FLIP" in note or "no step of its fine-tune" in note


def test_the_oidn_partners_hdr_flip_leaves_black_references_to_relmse():
    """On a black reference HDR-FLIP takes its exposure from the output, so an output of 1e-9 scores near 1: such
    rows (an interior's specular val rows, 31% of them) would outweigh every lit one in the step ranking."""
    from admc.common.metrics import hdr_flip
    from admc.model.training.oidn_partner import _mean_flip

    lit = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0)).double() + 0.1
    black = torch.zeros(2, 3, 16, 16, dtype=torch.float64)
    haze = torch.full_like(black, 1e-9)
    assert hdr_flip(haze[0].numpy().transpose(1, 2, 0), black[0].numpy().transpose(1, 2, 0)) > 0.5
    reference, output = torch.cat([lit, black]), torch.cat([lit, haze])
    assert _mean_flip(output, reference) == 0.0  # the lit rows are exact
    # the same float32 images as _mean_flip scores: only np.mean's summation order may differ
    assert _mean_flip(torch.cat([lit * 1.5, haze]), reference) == pytest.approx(
        np.mean(
            [hdr_flip((1.5 * x).float().numpy().transpose(1, 2, 0), x.float().numpy().transpose(1, 2, 0)) for x in lit]
        )
    )
    assert _mean_flip(haze, black) == 0.0  # no lit row: the metric is neutral (its ratio to step 0 is 1)


def test_the_oidn_partner_trains_in_float32_channels_last_whatever_the_runs_precision(store):
    """OIDN's networks fine-tune and validate in float32 (the OIDN library runs them so; trained in bf16 autocast
    they left 3-5% more HDR-FLIP on a product's test frames: docs/results/2026-12-06-fine-tuned-oidn.md), in
    channels_last (1.35x the steps of NCHW on 2 cores), even where train.precision runs admc's networks in bf16."""
    from admc.model.training.oidn_partner import finetune_partner, start_partner

    cpu = torch.device("cpu")
    settings = dataclasses.replace(SETTINGS, precision="bfloat16", val_every=1, oidn_blend=True, oidn_minutes=0.01)
    readers = {"diffuse": PatchReader(store, "train", branch="diffuse")}
    val = {"diffuse": load_rows(PatchReader(store, "val", branch="diffuse"), 4)}
    partner = start_partner(["diffuse"], settings, None, cpu)
    net = partner.nets["diffuse"]
    assert net.enc_conv0.weight.is_contiguous(memory_format=torch.channels_last)
    seen = []
    net.enc_conv0.register_forward_hook(lambda module, inputs, output: seen.append((module.training, output.dtype)))
    finetune_partner(partner, settings, readers, val, cpu, save=lambda: None, show=lambda line: None)
    assert partner.step >= 1 and partner.done
    assert {training for training, _ in seen} == {True, False}  # training steps and validations both ran
    assert {dtype for _, dtype in seen} == {torch.float32}
    assert all(math.isfinite(s["relmse"]) for s in partner.scores["diffuse"].values())


def test_an_older_admcs_oidn_partner_state_is_refused_with_one_message():
    """Before the candidates, a checkpoint held one Adam for both OIDN networks: such a state cannot resume."""
    from admc.model.training.oidn_partner import start_partner

    old = {"nets": {}, "optimizer": {}, "best": {}, "best_step": {}, "scores": {}, "step": 3, "seconds": 1.0}
    partner = start_partner(["specular"], SETTINGS, None, torch.device("cpu"))
    with pytest.raises(TrainingError, match="written by an older admc, whose state this one cannot resume"):
        partner.load_state_dict({**old, "done": False})
    relmse_only = {**old, "optimizers": {}, "scores": {"specular": {0: 0.01}}}  # before HDR-FLIP could rank steps
    with pytest.raises(TrainingError, match="written by an older admc, whose state this one cannot resume"):
        partner.load_state_dict({**relmse_only, "done": False})


def test_oidn_minutes_without_a_blend_or_in_several_processes_is_refused(store, tmp_path):
    from admc.model.training.distributed import check_world

    settings = dataclasses.replace(SETTINGS, oidn_minutes=1.0)
    with pytest.raises(ValueError, match=r"oidn_minutes: is 1: .* oidn_blend is false"):
        train(store, tmp_path / "refused", settings, TINY, progress=False)
    assert not (tmp_path / "refused" / "checkpoint.pt").exists()
    with pytest.raises(TrainingError, match=r"'train.oidn_minutes': OIDN's fine-tune runs in one process, not 2"):
        check_world(dataclasses.replace(settings, oidn_blend=True), TINY, 2)


def test_the_moving_average_follows_the_weights_with_a_ramped_decay(store):
    torch.manual_seed(0)
    settings = dataclasses.replace(SETTINGS, ema=0.5, l1_warmup_steps=10, head_tail_start_step=0)
    trainer = BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
    source = BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
    trainer.load_networks(source.generator.state_dict(), source.critic.state_dict(), "source")
    assert_states_equal(trainer.average.state_dict(), source.generator.state_dict())  # starts at loaded weights
    expected = snapshot(trainer.generator)
    for n in range(3):
        assert trainer.step(n, [batch_of(store)])[0]
        decay = min(0.5, (1 + n) / (10 + n))  # 0.1, 0.18, 0.25: below ema while the average is young
        expected = {k: decay * expected[k] + (1 - decay) * v for k, v in trainer.generator.state_dict().items()}
    # lerp and the explicit sum round differently: a few float32 ulps of weights below 1
    for key, value in trainer.average.state_dict().items():
        torch.testing.assert_close(value, expected[key], rtol=1e-5, atol=1e-6)
    assert trainer.shipped_generator is trainer.average and trainer.average_updates == 3
    assert not torch.equal(trainer.average.head.weight, trainer.generator.head.weight)


def test_the_moving_average_is_checkpointed_resumed_and_shipped(store, tmp_path):
    settings = dataclasses.replace(SETTINGS, ema=0.9, val_every=0)
    whole = train(store, tmp_path / "whole", settings, TINY, progress=False)
    train(store, tmp_path / "split", dataclasses.replace(settings, steps=4), TINY, progress=False)
    second = train(store, tmp_path / "split", settings, TINY, resume=True, progress=False)
    a, b = load_checkpoint(whole.checkpoint), load_checkpoint(second.checkpoint)
    assert_states_equal(a["branches"], b["branches"])
    shipped = load_weights(whole.weights)["branches"]
    for branch in ("diffuse", "specular"):
        state = a["branches"][branch]
        assert state["average_updates"] == 2 + 4  # the L1 and adversarial steps' generator updates
        for key, value in state["average"].items():
            assert torch.equal(shipped[branch]["generator"][key], value.half()), key
        assert not torch.equal(state["average"]["head.weight"], state["generator"]["head.weight"])
    nets, _, _ = read_networks(whole.checkpoint)  # denoising or fine-tuning from the checkpoint takes the average
    assert_states_equal(nets["specular"]["generator"], a["branches"]["specular"]["average"])


def test_resume_in_another_precision_continues_and_says_so(store, tmp_path):
    first = train(store, tmp_path / "run", dataclasses.replace(SETTINGS, steps=4, val_every=0), TINY, progress=False)
    assert load_checkpoint(first.checkpoint)["precision"] == "float32" and not first.notes
    second = train(
        store,
        tmp_path / "run",
        dataclasses.replace(SETTINGS, precision="bfloat16", val_every=0),
        TINY,
        resume=True,
        progress=False,
    )
    assert second.step == 7 and load_checkpoint(second.checkpoint)["precision"] == "bfloat16"
    assert any("ran in float32, this run continues in bfloat16" in note for note in second.notes)


# bf16 keeps 8 significant bits (unit roundoff u = 2^-8); each of the generator's D = 2 * blocks + 4
# chained 3x3 convs rounds its inputs and output (~2u of its output), so the outputs, and with them the
# L1 loss, move by at most 2 * D * u of the output magnitude from float32.
BF16_U = 2.0**-8


def test_bfloat16_steps_run_in_bf16_and_keep_float32_weights_and_losses(store):
    batch = batch_of(store)
    runs = {}
    for precision in PRECISIONS:
        torch.manual_seed(0)
        settings = dataclasses.replace(
            SETTINGS,
            l1_warmup_steps=0,
            critic_only_steps=0,
            critic_steps_per_g=1,
            head_tail_start_step=0,
            precision=precision,
        )
        trainer = BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
        dtypes = []
        trainer.generator.register_forward_hook(lambda m, i, out: dtypes.append(out.dtype))
        fake = trainer.generator(batch["noisy"], batch["features"]).detach()
        ok, losses = trainer.step(0, [batch])
        assert ok and all(np.isfinite(v) for v in losses.values())
        runs[precision] = losses, fake
        assert set(dtypes[1:]) == {getattr(torch, precision)}  # the generator ran in the asked precision
        assert trainer.generator.training and trainer.critic.training
        for net in (trainer.generator, trainer.critic):
            assert {p.dtype for p in net.parameters()} == {torch.float32}  # master weights
            kernels = [p for p in net.parameters() if p.dim() == 4]
            assert kernels and all(p.is_contiguous(memory_format=torch.channels_last) for p in kernels)
        for opt in trainer.optimizers.values():
            assert {v.dtype for st in opt.state.values() for k, v in st.items() if k != "step"} == {torch.float32}
    (low, fake), (exact, _) = runs["bfloat16"], runs["float32"]
    bound = 2 * (2 * TINY.blocks + 4) * BF16_U * float(fake.abs().max())
    assert 0 < abs(low["l1"] - exact["l1"]) <= bound  # bf16 really ran, and within its precision


def test_resume_refuses_changed_settings_and_a_missing_checkpoint(store, tmp_path):
    with pytest.raises(CheckpointError, match="checkpoint.pt: no such file"):
        train(store, tmp_path / "none", SETTINGS, TINY, resume=True, progress=False)
    train(store, tmp_path / "run", dataclasses.replace(SETTINGS, steps=2, val_every=0), TINY, progress=False)
    with pytest.raises(ValueError, match=r"\['batch_size'\] differ"):
        train(store, tmp_path / "run", dataclasses.replace(SETTINGS, batch_size=4), TINY, resume=True, progress=False)
    with pytest.raises(ValueError, match="exists: pass resume=True"):
        train(store, tmp_path / "run", SETTINGS, TINY, progress=False)


def test_a_checkpoint_older_than_a_train_setting_resumes_at_that_settings_default(store, tmp_path):
    """A checkpoint written before a train key existed ran at the key's default: resuming with the default
    continues, resuming with another value is refused naming the key."""
    settings = dataclasses.replace(SETTINGS, steps=2, val_every=0)
    train(store, tmp_path / "run", settings, TINY, progress=False)
    checkpoint = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    del checkpoint["settings"]["l1_floor"]
    save_checkpoint(tmp_path / "run" / "checkpoint.pt", checkpoint)
    with pytest.raises(ValueError, match=r"\['l1_floor'\] differ"):
        train(
            store,
            tmp_path / "run",
            dataclasses.replace(settings, steps=3, l1_floor=0.1),
            TINY,
            resume=True,
            progress=False,
        )
    assert (
        train(store, tmp_path / "run", dataclasses.replace(settings, steps=3), TINY, resume=True, progress=False).step
        == 3
    )


def test_a_run_of_bad_steps_stops_and_keeps_the_last_good_checkpoint(store_copy, tmp_path):
    out = tmp_path / "run"
    settings = dataclasses.replace(SETTINGS, steps=4, val_every=0)
    train(store_copy, out, settings, TINY, progress=False)
    good = load_checkpoint(out / "checkpoint.pt")
    root = zarr.open_group(store=LocalStore(store_copy), mode="r+")
    for scene in PatchReader(store_copy, "train").scenes:  # corrupt every diffuse training patch in place
        array = root[f"train/{scene}/noisy_diffuse"]
        array[...] = np.full(array.shape, np.nan, dtype=np.float16)
    with pytest.raises(TrainingDiverged, match=r"diffuse: 3 consecutive steps .* \(step 4\)"):
        train(
            store_copy,
            out,
            dataclasses.replace(settings, steps=20, checkpoint_every=1),
            TINY,
            resume=True,
            progress=False,
        )
    kept = load_checkpoint(out / "checkpoint.pt")
    assert kept["step"] == 4
    assert_states_equal(kept["branches"], good["branches"])


def test_a_store_with_another_transform_is_refused(store_copy, tmp_path):
    root = zarr.open_group(store=LocalStore(store_copy), mode="r+")
    transform = dict(root.attrs["transform"])
    transform["eps"] = 0.01
    root.attrs["transform"] = transform
    with pytest.raises(PatchStoreError, match=r"refused for this code's transform spec: .*eps"):
        train(store_copy, tmp_path / "run", SETTINGS, TINY, progress=False)


def test_missing_splits_and_branches(store_copy, tmp_path):
    for scene in PatchReader(store_copy, "train", branch="specular").scenes:
        shutil.rmtree(store_copy / "train" / scene)  # the train split keeps only diffuse-only scenes
    result = train(store_copy, tmp_path / "a", dataclasses.replace(SETTINGS, steps=1), TINY, progress=False)
    assert result.branches == ["diffuse"] and result.skipped_branches == ["specular"]
    assert any("no specular patches in the train split" in note for note in result.notes)
    for scene in PatchReader(store_copy, "val").scenes:
        shutil.rmtree(store_copy / "val" / scene)
    with pytest.raises(PatchStoreError, match="the val split has no diffuse patches"):
        train(store_copy, tmp_path / "b", SETTINGS, TINY, progress=False)


def test_finetune_starts_from_exported_weights(store, tmp_path):
    pre = train(store, tmp_path / "pre", dataclasses.replace(SETTINGS, steps=3, val_every=0), TINY, progress=False)
    shipped = load_weights(pre.weights)
    settings = dataclasses.replace(SETTINGS, steps=1, val_every=0, l1_warmup_steps=1, head_tail_start_step=100)
    fine = train(store, tmp_path / "fine", settings, TINY, stage="finetune", init_from=pre.weights, progress=False)
    state = load_checkpoint(fine.checkpoint)
    assert state["stage"] == "finetune" and state["init_from"] == str(pre.weights)
    for branch in ("diffuse", "specular"):
        # one L1 step with head/tail frozen: the head still holds the shipped (fp16) weights exactly
        got = state["branches"][branch]["generator"]["head.weight"]
        assert torch.equal(got, shipped["branches"][branch]["generator"]["head.weight"].float())
        assert torch.equal(
            state["branches"][branch]["critic"]["classifier.2.weight"],
            shipped["branches"][branch]["critic"]["classifier.2.weight"].float(),
        )
    with pytest.raises(ValueError, match=r"model settings differ from the configured ones in \['channels'\]"):
        train(
            store,
            tmp_path / "bad",
            settings,
            dataclasses.replace(TINY, channels=4),
            stage="finetune",
            init_from=pre.weights,
            progress=False,
        )
    with pytest.raises(ValueError, match="needs init_from"):
        train(store, tmp_path / "none", settings, TINY, stage="finetune", progress=False)


def test_checkpoint_round_trip_and_clear_errors(tmp_path):
    state = {"step": 3, "w": torch.randn(4, 5), "nested": {"t": (1, 2.5, "x"), "milestones": [5, 9]}}
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, state)
    loaded = load_checkpoint(path)
    assert loaded["step"] == 3 and torch.equal(loaded["w"], state["w"]) and loaded["nested"] == state["nested"]
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temp files left
    with pytest.raises(CheckpointError, match="missing.pt: no such file"):
        load_checkpoint(tmp_path / "missing.pt")
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="truncated.pt: not a readable torch file"):
        load_checkpoint(truncated)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.ones(2)}, other)
    with pytest.raises(CheckpointError, match="other.pt: not an admc-checkpoint file"):
        load_checkpoint(other)


def test_exported_weights_are_fp16_and_load_back(tmp_path):
    torch.manual_seed(0)
    trainer = BranchTrainer("diffuse", TINY, SETTINGS, 32, torch.device("cpu"))
    nets = {"diffuse": {"generator": trainer.generator.state_dict(), "critic": trainer.critic.state_dict()}}
    path = tmp_path / "weights.pt"
    export_weights(path, nets, {"model": dataclasses.asdict(TINY)})
    loaded = load_weights(path)
    assert loaded["metadata"]["model"]["channels"] == 8
    half = loaded["branches"]["diffuse"]["generator"]["head.weight"]
    assert half.dtype == torch.float16
    assert torch.equal(half, trainer.generator.head.weight.detach().half())
    fresh = BranchTrainer("diffuse", TINY, SETTINGS, 32, torch.device("cpu"))
    fresh.load_networks(loaded["branches"]["diffuse"]["generator"], loaded["branches"]["diffuse"]["critic"], "x")
    assert torch.allclose(fresh.generator.head.weight, trainer.generator.head.weight, rtol=1e-3, atol=1e-6)
    wide = BranchTrainer("diffuse", dataclasses.replace(TINY, channels=4), SETTINGS, 32, torch.device("cpu"))
    with pytest.raises(ValueError, match="weights.pt: diffuse generator weights do not fit"):
        wide.load_networks(
            loaded["branches"]["diffuse"]["generator"], loaded["branches"]["diffuse"]["critic"], str(path)
        )
    with pytest.raises(CheckpointError, match="not an admc-checkpoint file"):
        load_checkpoint(path)


def test_settings_check_names_the_field():
    for settings in (*preset("paper"), *preset("default"), TINY, SETTINGS):
        settings.check()
    with pytest.raises(ValueError, match="^mode: 'film' is not one of"):
        dataclasses.replace(TINY, mode="film").check()
    with pytest.raises(ValueError, match="^lr_milestones: must be strictly increasing"):
        dataclasses.replace(SETTINGS, lr_milestones=(5, 3)).check()
    with pytest.raises(ValueError, match="^branches: must be distinct"):
        dataclasses.replace(SETTINGS, branches=("diffuse", "glossy")).check()
    with pytest.raises(ValueError, match="^batch_size: must be an int >= 1"):
        dataclasses.replace(SETTINGS, batch_size=0).check()
    with pytest.raises(ValueError, match="^precision: 'float16' is not one of"):
        dataclasses.replace(SETTINGS, precision="float16").check()
    with pytest.raises(ValueError, match=r"^ema: must be in \[0, 1\), got 1"):
        dataclasses.replace(SETTINGS, ema=1).check()
    phases = [SETTINGS.phase(s) for s in range(5)]
    assert phases == ["l1", "l1", "critic", "adversarial", "adversarial"]


def test_weights_from_another_patch_size_name_tile_patch_size():
    settings = dataclasses.replace(SETTINGS, steps=1)
    trained = BranchTrainer("diffuse", TINY, settings, 64, torch.device("cpu"))
    other = BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
    with pytest.raises(CheckpointError, match=r"diffuse critic weights do not fit .* tile.patch_size = 32"):
        other.load_networks(trained.generator.state_dict(), trained.critic.state_dict(), "w.pt")


@pytest.fixture(scope="module")
def noise_store(tmp_path_factory, variant):
    """The tiny store with each branch's noise map per row (tile.noise_maps), what model.noise_input reads."""
    return build_tiny_store(tmp_path_factory.mktemp("noise_store"), size=64, patch=32, extra=["tile.noise_maps=true"])


def test_finetune_adds_the_noise_input_to_weights_trained_without_it(noise_store, tmp_path):
    pre = train(
        noise_store, tmp_path / "pre", dataclasses.replace(SETTINGS, steps=2, val_every=0), TINY, progress=False
    )  # a store with noise maps trains models without the input too
    shipped = load_weights(pre.weights)["branches"]
    noise_model = dataclasses.replace(TINY, noise_input=True)
    still = dataclasses.replace(
        SETTINGS,
        steps=1,
        val_every=0,
        l1_warmup_steps=1,
        head_tail_start_step=100,
        lr_g_diffuse=1e-12,
        lr_g_specular=1e-12,
    )
    fine = train(
        noise_store, tmp_path / "fine", still, noise_model, stage="finetune", init_from=pre.weights, progress=False
    )
    state = load_checkpoint(fine.checkpoint)
    assert state["model"]["noise_input"] is True
    for branch in ("diffuse", "specular"):
        old = shipped[branch]["generator"]["encoder.layers.0.weight"].float()
        new = state["branches"][branch]["generator"]["encoder.layers.0.weight"]
        assert new.shape == (old.shape[0], 8, 3, 3)
        # one Adam step of 5e-12 (the body's lr) moves each weight by at most ~5e-12: from the saved
        # weights, and from 0 on the noise channel
        torch.testing.assert_close(new[:, :7], old, rtol=0, atol=1e-10)
        assert new[:, 7].abs().max() < 1e-10
    with pytest.raises(ValueError, match=r"differ from the configured ones in \['noise_input'\]"):
        train(noise_store, tmp_path / "back", still, TINY, stage="finetune", init_from=fine.weights, progress=False)

    # a real step: the noise channel's weights leave exactly 0, so the networks learn from the map. Adam's
    # first step moves a weight by lr * |g| / (|g| + 1e-8): nonzero for any nonzero gradient, below the
    # body's lr (5 x 1e-4). (The tiny nets' encoder gradients are ~1e-12, so the steps are ~1e-7.)
    moving = dataclasses.replace(SETTINGS, steps=1, val_every=0, l1_warmup_steps=1, head_tail_start_step=100)
    stepped = load_checkpoint(
        train(
            noise_store, tmp_path / "step", moving, noise_model, stage="finetune", init_from=pre.weights, progress=False
        ).checkpoint
    )
    for branch in ("diffuse", "specular"):
        weights = stepped["branches"][branch]["generator"]["encoder.layers.0.weight"][:, 7]
        assert torch.count_nonzero(weights) == weights.numel()
        assert weights.abs().max() <= moving.lr_g_diffuse * moving.body_lr_factor


def test_a_noise_input_model_refuses_a_store_without_noise_maps(store, tmp_path):
    model = dataclasses.replace(TINY, noise_input=True)
    with pytest.raises(
        PatchStoreError,
        match=rf"patch store {store}: scene train/\S+ has no noise maps.*"
        r"admc-pipe dataset",
    ):
        train(store, tmp_path / "run", dataclasses.replace(SETTINGS, steps=1, val_every=0), model, progress=False)


def _teacher_weights(tmp_path, model, seed=3):
    """fp16 weights of a randomly initialised `model` (both branches): a teacher to distil from."""
    from admc.model.nets.backbones import build_generator
    from admc.model.nets.critic import Critic

    torch.manual_seed(seed)
    branches = {}
    for b in ("diffuse", "specular"):
        generator = build_generator(model)
        with torch.no_grad():  # far from the student's near-zero start, so there is a gap to close
            for p in generator.parameters():
                p.normal_(0.0, 0.1)
        branches[b] = {"generator": generator.state_dict(), "critic": Critic(model, 32).state_dict()}
    path = tmp_path / "teacher.pt"
    export_weights(path, branches, {"model": dataclasses.asdict(model), "transform": {}})
    return path


def test_distillation_pulls_a_slimmer_student_toward_its_teacher(store, tmp_path):
    """train.distill_from: the loss gains L1(student, teacher) in the log domain, and with only that term
    weighted the slim student's outputs move toward the (wider) teacher's."""
    teacher_model = dataclasses.replace(TINY, input_skip=True)  # outputs near the input, not clipped to 0
    teacher_path = _teacher_weights(tmp_path, teacher_model)
    student = dataclasses.replace(teacher_model, cfm_per_block=1, condition_layers=1)
    settings = dataclasses.replace(
        SETTINGS,
        adversarial=False,
        head_tail_start_step=0,
        lr_g_diffuse=2e-3,
        l1_weight=1e-9,
        distill_from=str(teacher_path),
        distill_weight=1.0,
    )
    torch.manual_seed(0)
    trainer = BranchTrainer("diffuse", student, settings, 32, torch.device("cpu"))
    batch = batch_of(store)
    inputs = (batch["noisy"], batch["features"])
    with torch.no_grad():
        want = trainer.teacher(*inputs)
        before = float((trainer.generator(*inputs) - want).abs().mean())
    parts = [trainer.step(i, [batch])[1] for i in range(60)]
    # the logged term is exactly the mean log-domain gap (l1_floor 1: the networks' own log1p values)
    assert abs(parts[0]["distill"] - before) < 1e-6 * max(1.0, before)
    with torch.no_grad():
        after = float((trainer.generator(*inputs) - want).abs().mean())
    # Measured: the gap falls from 0.10 to 0.03 in 60 steps at this learning rate; half is a wide margin.
    assert after < 0.5 * before, (before, after)
    assert not any(p.requires_grad for p in trainer.teacher.parameters())


def test_a_teacher_that_reads_other_inputs_or_is_missing_is_refused_naming_the_key(store, tmp_path):
    refiner = _teacher_weights(tmp_path, dataclasses.replace(TINY, base="oidn"))
    settings = dataclasses.replace(SETTINGS, distill_from=str(refiner))
    with pytest.raises(
        ValueError,
        match=r"^train.distill_from: .*teacher.pt has model.base = 'oidn', this "
        r"config 'noisy': a teacher must read the same inputs",
    ):
        BranchTrainer("diffuse", TINY, settings, 32, torch.device("cpu"))
    missing = dataclasses.replace(SETTINGS, distill_from=str(tmp_path / "nope.pt"))
    with pytest.raises(ValueError, match=r"^train.distill_from: .*nope.pt is not a file"):
        BranchTrainer("diffuse", TINY, missing, 32, torch.device("cpu"))
    with pytest.raises(ValueError, match=r"^distill_weight: must be >= 0"):
        dataclasses.replace(SETTINGS, distill_weight=-1.0).check()


SLIM_WEIGHTS = Path(__file__).resolve().parents[1] / "scripts" / "slim_weights.py"


def test_slim_weights_script_writes_a_fine_tuning_start_of_the_slim_model(store, tmp_path):
    """scripts/slim_weights.py on real weights and a real store: slim weights that a fine-tune of the slim
    [model] accepts as --init; a request that is not slimmer, or a missing file, is one line, no traceback."""
    import subprocess
    import sys

    pre = train(store, tmp_path / "pre", dataclasses.replace(SETTINGS, steps=2, val_every=0), TINY, progress=False)
    out = tmp_path / "slim.pt"
    done = subprocess.run(
        [sys.executable, str(SLIM_WEIGHTS), str(pre.weights), str(store), str(out), "--patches", "4"],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    assert "diffuse: slim output differs from the full one by" in done.stdout
    slim = dataclasses.replace(TINY, cfm_per_block=1, condition_layers=1)
    _, saved, _ = read_networks(out)
    assert ModelSettings.from_saved(saved) == slim
    settings = dataclasses.replace(SETTINGS, steps=1, val_every=0, distill_from=str(pre.weights))
    train(store, tmp_path / "fine", settings, slim, stage="finetune", init_from=out, progress=False)
    for args, message in (
        ([str(out), str(store), str(tmp_path / "again.pt")], "which is not slimmer"),
        ([str(tmp_path / "none.pt"), str(store), str(tmp_path / "x.pt")], "none.pt: no such file"),
    ):
        done = subprocess.run([sys.executable, str(SLIM_WEIGHTS), *args], capture_output=True, text=True)
        assert done.returncode == 1 and message in done.stderr and "Traceback" not in done.stderr, done.stderr
