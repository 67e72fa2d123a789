"""A trained generator whose outputs a training run also learns from (train.distill_from): distillation.

A smaller network (fewer CFM layers: model.cfm_per_block, model.condition_layers) learns faster from a
teacher's outputs than from the references alone: the teacher's are noise-free and already carry what
its long training learnt, so the student's loss has one more, smooth target per pixel (Hinton et al. 2015).
The teacher reads the same inputs as the student (base and noise input must match); its size may differ.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
from torch import nn

from admc.errors import TrainingError
from admc.stores.checkpoints import load_network, read_networks

from ..nets.backbones import build_generator
from ..nets.settings import ModelSettings
from ..precision import MEMORY_FORMAT

SAME_INPUTS = ("base", "noise_input")
"""[model] keys the teacher must share with the student: they decide what the generator is called with."""


def load_teacher(path: str, branch: str, model: ModelSettings, device: torch.device) -> nn.Module:
    """The frozen, eval-mode generator of `branch` in the weights or checkpoint at `path`."""
    if not Path(path).is_file():
        raise TrainingError(f"train.distill_from: {path} is not a file (weights or a checkpoint)")
    nets, saved, _ = read_networks(path)
    teacher_model = ModelSettings.from_saved(saved)
    differ = [k for k in SAME_INPUTS if getattr(teacher_model, k) != getattr(model, k)]
    if differ:
        raise TrainingError(
            f"train.distill_from: {path} has "
            + ", ".join(f"model.{k} = {getattr(teacher_model, k)!r}" for k in differ)
            + ", this config "
            + ", ".join(f"{getattr(model, k)!r}" for k in differ)
            + ": a teacher must read the same inputs"
        )
    if branch not in nets:
        raise TrainingError(f"train.distill_from: {path} has no {branch} branch")
    teacher = build_generator(teacher_model)
    load_network(
        teacher, nets[branch]["generator"], f"{path} ({branch} generator)", str(dataclasses.asdict(teacher_model))
    )
    teacher = teacher.to(device, memory_format=MEMORY_FORMAT).eval()
    for p in teacher.parameters():
        p.requires_grad_(False)
    return teacher
