"""Where a training run starts: the checks an exact resume needs, the weights a fine-tuning starts from,
and the random-number state a checkpoint carries."""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import numpy as np
import torch

from admc.common.diff import differing_keys
from admc.common.layout import N_FEATURES
from admc.errors import TrainingError
from admc.stores.checkpoints import read_networks

from ..nets.generator import COLOR_CHANNELS
from ..nets.settings import ModelSettings
from ..train_settings import TrainSettings

# Settings a resumed run may change without changing what it computes.
# precision: weights, Adam states and losses stay float32 under bf16 autocast, so a run resumed in the
# other precision continues correctly, just not bit-identically (said in a note), as after a device change.
RESUMABLE_CHANGES = (
    "steps",
    "minutes",
    "oidn_blend",
    "val_every",
    "val_patches",
    "select_z",
    "checkpoint_every",
    "log_every",
    "num_workers",
    "threads",
    "device",
    "precision",
    "max_bad_steps",
)


def rng_state() -> dict:
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    state = {
        "python": random.getstate(),
        "torch": torch.get_rng_state(),
        "numpy": (kind, keys.tolist(), pos, has_gauss, cached),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    torch.set_rng_state(state["torch"])
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, np.array(keys, dtype=np.uint32), pos, has_gauss, cached))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def check_resumable(
    checkpoint: dict, path: Path, settings: TrainSettings, model: ModelSettings, stage: str, fingerprint: str
) -> None:
    if checkpoint["stage"] != stage:
        raise TrainingError(f"{path}: is a {checkpoint['stage']!r} checkpoint, cannot resume it as {stage!r}")
    saved = dataclasses.asdict(ModelSettings.from_saved(checkpoint["model"]))
    diff = differing_keys(saved, dataclasses.asdict(model))
    if diff:
        raise TrainingError(f"{path}: model settings differ from the checkpoint's in {diff}")
    saved, now = checkpoint["settings"], dataclasses.asdict(settings)
    defaults = dataclasses.asdict(TrainSettings())  # a key newer than the checkpoint ran at its default
    diff = [k for k in now if k not in RESUMABLE_CHANGES and saved.get(k, defaults[k]) != now[k]]
    if diff:
        raise TrainingError(
            f"{path}: train settings {diff} differ from the checkpoint's; an exact resume allows "
            f"changing only {list(RESUMABLE_CHANGES)}"
        )
    if checkpoint["store"]["fingerprint"] != fingerprint:
        raise TrainingError(
            f"{path}: the patch store changed since this checkpoint (scenes or attributes differ); "
            "resume needs the same data: start a 'finetune' from the checkpoint instead"
        )


def say_precision_change(checkpoint: dict, precision: str, say) -> None:
    """Note a resume in another precision than the checkpoint's steps ran in (older checkpoints do not
    say which)."""
    before = checkpoint.get("precision")
    if before is not None and before != precision:
        say(
            f"the checkpoint's steps ran in {before}, this run continues in {precision}: training goes on "
            f"from the same state, but not bit-identically to an uninterrupted {before} run"
        )


def load_init(init_from: Path | None, model: ModelSettings) -> tuple[dict, dict, str]:
    """(branch -> {"generator", "critic"}, transform spec, description) from a checkpoint or fp16 weights."""
    if init_from is None:
        raise TrainingError("stage 'finetune' needs init_from (a checkpoint or exported weights)")
    init_from = Path(init_from)
    nets, saved_model, transform = read_networks(init_from)
    saved = dataclasses.asdict(ModelSettings.from_saved(saved_model))
    refiners = saved["base"] != "noisy" and model.base != "noisy"  # the same network, bases of another OIDN quality
    if saved["base"] != model.base and not refiners:
        raise TrainingError(
            f"{init_from}: was trained with model.base = {saved['base']!r}, this config has "
            f"model.base = {model.base!r}; fine-tune from weights of the same base (the shipped "
            "ones for either base are found automatically when --init is left out)"
        )
    diff = [key for key in differing_keys(saved, dataclasses.asdict(model)) if key != "base"]
    start = f"{init_from}" + ("" if saved["base"] == model.base else f" (a refiner of model.base {saved['base']!r})")
    if diff == ["noise_input"] and model.noise_input:
        nets = {
            branch: {**state, "generator": with_noise_input(state["generator"], model)}
            for branch, state in nets.items()
        }
        return nets, transform, f"{start} (the noise input added, its weights starting at 0)"
    if diff:
        raise TrainingError(f"{init_from}: its model settings differ from the configured ones in {diff}")
    return nets, transform, start


def with_noise_input(state: dict, model: ModelSettings) -> dict:
    """A generator's weights given one more feature channel, the noise map, with zero weights on it: the
    widened generator computes exactly what the saved one did, and training starts from there."""
    features_at = {"encoder.layers.0.weight": N_FEATURES}  # encoder input: features [+ noise], then a refiner's noisy
    if model.mode == "concat":
        features_at["head.weight"] = COLOR_CHANNELS + N_FEATURES  # head input: noisy, features [+ noise]
    out = dict(state)
    for key, at in features_at.items():
        if key in out:
            w = out[key]
            zeros = torch.zeros((w.shape[0], 1, *w.shape[2:]), dtype=w.dtype)
            out[key] = torch.cat([w[:, :at], zeros, w[:, at:]], dim=1)
    return out
