"""Training ships each branch's best networks by validation, not its last, and a fine-tuning that does
not beat its starting weights by more than the val patches' noise ships them unchanged (real tiny store,
real training steps)."""

import csv
import dataclasses
import math
import shutil

import pytest
import torch
import zarr
from torch import nn
from zarr.storage import LocalStore

from conftest import build_tiny_store
from admc.model.nets.backbones import build_generator
from admc.model.nets.settings import ModelSettings
from admc.model.training.data import load_rows
from admc.model.training.selection import BestNetworks, improvement_z, selection_values
from admc.model.train_settings import TrainSettings
from admc.model.training.trainer import train
from admc.model.training.validation import baseline_scores, validate
from admc.stores.checkpoints import load_checkpoint, load_weights
from admc.stores.patches import PatchReader, list_scenes

TINY = ModelSettings(channels=8, blocks=2, cond_channels=8, encoder_channels=16, critic_channels=4, input_skip=True)
SETTINGS = TrainSettings(
    steps=6,
    batch_size=2,
    l1_warmup_steps=6,
    critic_only_steps=0,
    lr_g_diffuse=1e-4,
    lr_g_specular=1e-4,
    lr_d=1e-4,
    head_tail_start_step=0,
    lr_milestones=(100,),
    val_every=2,
    val_patches=8,
    checkpoint_every=2,
    log_every=2,
    num_workers=0,
    threads=0,
    device="cpu",
    seed=3,
    max_bad_steps=3,
)


@pytest.fixture(scope="module")
def store(tmp_path_factory, variant):
    return build_tiny_store(tmp_path_factory.mktemp("selection_store"), size=64, patch=32)


def patches(*values):
    return torch.tensor(values, dtype=torch.float64)


def test_best_networks_keep_the_lowest_value_and_the_earlier_step_on_ties():
    best, net = BestNetworks(), nn.Linear(2, 1)
    assert best.offer("diffuse", 0, patches(0.5, 0.5), net, net)
    with torch.no_grad():
        net.weight.fill_(7.0)
    assert not best.offer("diffuse", 2, patches(0.4, 0.6), net, net)
    assert not best.offer("diffuse", 4, patches(0.6, 0.6), net, net)
    kept = best.networks("diffuse", net, net)["generator"]["weight"]
    assert not torch.equal(kept, net.weight)  # the copy from step 0, not the live module
    assert best.offer("diffuse", 6, patches(0.3, 0.5), net, net) and best.best["diffuse"].step == 6
    assert best.networks("specular", net, net)["generator"] is not None  # never validated: the given ones
    again = BestNetworks()
    again.load_state_dict(best.state_dict())
    assert again.best["diffuse"].step == 6 and again.best["diffuse"].value == 0.4


def test_improvement_z_is_the_paired_mean_difference_over_its_standard_error():
    start = patches(1.0, 2.0, 3.0, 4.0)
    # differences 0.1, 0.3, 0.1, 0.3: mean 0.2, sample std 0.11547, standard error 0.057735
    assert improvement_z(start, patches(0.9, 1.7, 2.9, 3.7)) == pytest.approx(0.2 / 0.057735, rel=1e-5)
    assert improvement_z(start, start - 0.5) == math.inf and improvement_z(start, start + 0.5) == -math.inf
    assert math.isnan(improvement_z(patches(1.0), patches(0.5)))


def test_guarded_starting_weights_give_way_only_to_a_significant_improvement():
    best, net = BestNetworks(min_z=2.0), nn.Linear(2, 1)
    start = patches(1.0, 2.0, 3.0, 4.0)
    assert best.offer("diffuse", 0, start, net, net, guard=True)
    noise = patches(0.8, 2.1, 2.9, 4.1)  # mean 0.025 lower, but the patches disagree: z = 0.33
    assert not best.offer("diffuse", 2, noise, net, net) and best.best["diffuse"].step == 0
    selected, notes = best.summary(4, {"diffuse": 2.475})
    assert selected["diffuse"]["step"] == 0
    assert "step 2 was 1% below the starting weights" in notes[0] and "within the noise" in notes[0]
    assert best.offer("diffuse", 4, patches(0.9, 1.8, 2.9, 3.8), net, net)  # every patch better: z = 5.2
    again = BestNetworks(min_z=2.0)
    again.load_state_dict(best.state_dict())  # a resumed run keeps guarding the same starting weights
    assert not again.offer("diffuse", 6, patches(0.5, 2.3, 2.8, 3.7), net, net)  # below step 4, but z = 1.03
    assert again.best["diffuse"].step == 4
    loose = BestNetworks(min_z=0.0)
    assert loose.offer("diffuse", 0, start, net, net, guard=True) and loose.offer("diffuse", 2, noise, net, net)


def glaring_targets(store, tmp_path):
    """A copy of the store whose train references are all glaring white: training on it can only make the
    generator worse on the (untouched) val split."""
    copy = tmp_path / "glaring.zarr"
    shutil.copytree(store, copy)
    for scene in list_scenes(copy, "train"):
        for name in ("ref_diffuse", "ref_specular"):
            if (copy / "train" / scene / name).is_dir():
                array = zarr.open_array(store=LocalStore(copy / "train" / scene / name), mode="r+")
                array[...] = 4.0  # log domain: ~50x the radiance of a mid-grey
    return copy


def test_a_finetuning_that_only_gets_worse_ships_its_starting_weights(store, tmp_path):
    pre = train(store, tmp_path / "pre", dataclasses.replace(SETTINGS, val_every=0), TINY, progress=False)
    worse = dataclasses.replace(SETTINGS, lr_g_diffuse=1e-3, lr_g_specular=1e-3)
    fine = train(
        glaring_targets(store, tmp_path),
        tmp_path / "fine",
        worse,
        TINY,
        stage="finetune",
        init_from=pre.weights,
        progress=False,
    )
    start, shipped = load_weights(pre.weights), load_weights(fine.weights)
    for branch in ("diffuse", "specular"):
        assert fine.selected[branch]["step"] == 0
        assert fine.validation[branch]["relmse"] > fine.selected[branch]["val_relmse"]
        for name, value in start["branches"][branch]["generator"].items():
            assert torch.equal(shipped["branches"][branch]["generator"][name], value), (branch, name)
    assert any("no step beat the starting weights" in note for note in fine.notes)
    assert shipped["metadata"]["selected"] == fine.selected
    # the checkpoint still holds the last state, so the run resumes where it stopped
    last = load_checkpoint(fine.checkpoint)["branches"]["diffuse"]["generator"]["head.weight"]
    assert not torch.equal(last.half(), start["branches"]["diffuse"]["generator"]["head.weight"])


def test_a_finetuning_within_the_val_noise_ships_its_starting_weights_and_says_so(store, tmp_path):
    pre = train(store, tmp_path / "pre", dataclasses.replace(SETTINGS, val_every=0), TINY, progress=False)
    faster = dataclasses.replace(SETTINGS, lr_g_diffuse=3e-3, lr_g_specular=3e-3, precision="float32")
    loose = train(
        store,
        tmp_path / "loose",
        dataclasses.replace(faster, select_z=0.0),
        TINY,
        stage="finetune",
        init_from=pre.weights,
        progress=False,
    )
    assert loose.selected["specular"]["step"] > 0  # the premise: a step has a far lower val mean (~30% here)
    strict = train(
        store,
        tmp_path / "strict",
        dataclasses.replace(faster, select_z=1e6),
        TINY,
        stage="finetune",
        init_from=pre.weights,
        progress=False,
    )
    assert strict.selected["specular"]["step"] == 0
    assert any(note.startswith("specular: step ") and "within the noise" in note for note in strict.notes)
    start, shipped = load_weights(pre.weights), load_weights(strict.weights)
    for name, value in start["branches"]["specular"]["generator"].items():
        assert torch.equal(shipped["branches"]["specular"]["generator"][name], value), name


def test_a_resumed_run_keeps_the_best_it_had_and_ships_what_one_run_ships(store, tmp_path):
    whole = train(store, tmp_path / "whole", SETTINGS, TINY, progress=False)
    train(store, tmp_path / "split", dataclasses.replace(SETTINGS, steps=4), TINY, progress=False)
    second = train(store, tmp_path / "split", SETTINGS, TINY, resume=True, progress=False)
    assert second.selected == whole.selected and set(whole.selected) == {"diffuse", "specular"}
    a, b = load_weights(whole.weights), load_weights(second.weights)
    for branch in ("diffuse", "specular"):
        for net in ("generator", "critic"):
            for name, value in a["branches"][branch][net].items():
                assert torch.equal(b["branches"][branch][net][name], value), (branch, net, name)


def test_the_relmse_ssim_value_weighs_each_error_by_the_inputs_mean():
    per_patch = {"relmse": patches(0.02, 0.04), "one_minus_ssim": patches(0.1, 0.1)}
    scores = {"noisy_relmse": 0.2, "noisy_one_minus_ssim": 0.5}
    assert selection_values("relmse", per_patch, scores).tolist() == [0.02, 0.04]
    assert selection_values("relmse+ssim", per_patch, scores).tolist() == pytest.approx([0.15, 0.2])
    # halving a patch's 1-SSIM counts as much as halving its relMSE when both are the same share of the input's
    halved = {"relmse": patches(0.02, 0.04), "one_minus_ssim": patches(0.1, 0.05)}
    assert selection_values("relmse+ssim", halved, scores)[1] < selection_values("relmse+ssim", per_patch, scores)[1]


def test_a_run_selecting_by_relmse_and_ssim_ships_the_step_it_names(store, tmp_path):
    settings = dataclasses.replace(SETTINGS, select_metric="relmse+ssim", ssim_weight=0.5, precision="float32")
    run = train(store, tmp_path / "run", settings, TINY, progress=False)
    logged = {}
    with open(run.out_dir / "metrics.csv") as f:
        for row in csv.DictReader(f):
            logged[(row["tag"], int(row["step"]))] = float(row["value"])
    for branch in ("diffuse", "specular"):
        chosen = run.selected[branch]
        assert set(chosen) == {"step", "val_relmse_ssim"}
        # the mean over patches of (relMSE / input's mean + 1-SSIM / input's mean) / 2 is linear in the patches
        val = {
            k: logged[(f"{branch}/val_{k}", chosen["step"])]
            for k in ("relmse", "noisy_relmse", "one_minus_ssim", "noisy_one_minus_ssim")
        }
        expected = (val["relmse"] / val["noisy_relmse"] + val["one_minus_ssim"] / val["noisy_one_minus_ssim"]) / 2
        assert chosen["val_relmse_ssim"] == pytest.approx(expected, rel=1e-5)
        assert {"l1", "ssim"} <= set(run.last_losses[branch])
    assert load_weights(run.weights)["metadata"]["selected"] == run.selected


@pytest.mark.parametrize("branch", ["diffuse", "specular"])
def test_the_baseline_is_the_input_scored_as_an_output_would_be(store, branch):
    # baseline_scores runs once per run; it must score exactly what validate would give a network that
    # returns its input: a skip generator whose correction is zero
    rows = load_rows(PatchReader(store, "val", branch=branch), 8)
    generator = build_generator(TINY)
    with torch.no_grad():
        for p in generator.tail[-2].parameters():
            p.zero_()
    scores, per_patch, _ = validate(generator, rows, branch, 4, torch.device("cpu"))
    baseline = baseline_scores(rows, branch)
    assert set(baseline) == {"noisy_psnr", "noisy_relmse", "noisy_one_minus_ssim"}
    for key in ("psnr", "relmse", "one_minus_ssim"):
        assert scores[key] == pytest.approx(baseline[f"noisy_{key}"], rel=1e-9)
    assert per_patch["relmse"].shape == (len(rows["noisy"]),)
