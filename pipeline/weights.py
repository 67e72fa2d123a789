"""Where weights are and how they load: a config's own training runs, the shipped weights, one file.

Every command that needs weights (train's fine-tuning start, denoise, eval) finds them here.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import replace
from importlib import resources
from pathlib import Path

from admc.common.diff import differing_keys
from admc.common.layout import BASE_QUALITIES
from admc.errors import StageError
from admc.model.inference.denoiser import FullImageDenoiser, load_denoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.nets.settings import ModelSettings
from admc.model.precision import resolve_device
from admc.pipeline.config import Config
from admc.stores.checkpoints import WEIGHTS_NAME

WEIGHTS_DIR = Path(resources.files("admc.weights"))
"""The shipped weights, package data of admc.weights: found from an editable or a plain install."""


def _shipped(weights_dir: Path) -> list[tuple[Path, ModelSettings]]:
    """(file, architecture) of every entry of weights/manifest.json."""
    manifest = weights_dir / "manifest.json"
    if not manifest.is_file():
        return []
    return [
        (weights_dir / entry["file"], ModelSettings.from_saved(entry["model"]))
        for entry in json.loads(manifest.read_text())["weights"]
    ]


def shipped_weights(model: ModelSettings, weights_dir: Path = WEIGHTS_DIR) -> Path | None:
    """The shipped fp16 weights whose architecture is `model`, listed in weights/manifest.json; failing
    that, a fine-tuning start: for a model.noise_input, those of the same architecture without it (fine-tuning
    then adds the input with zero weights, which computes what they did: resume.load_init), and for a
    refiner, one of the same network refining bases of another OIDN quality."""
    shipped = _shipped(weights_dir)
    exact = next((path for path, saved in shipped if saved == model), None)
    if exact is not None:
        return exact
    starts = [dataclasses.replace(model, noise_input=False)] if model.noise_input else []
    if model.base != "noisy":
        starts += [dataclasses.replace(start, base=base) for start in [model, *starts] for base in BASE_QUALITIES]
    return next((path for start in starts for path, saved in shipped if saved == start), None)


def shipped_mismatch(model: ModelSettings, weights_dir: Path = WEIGHTS_DIR) -> str:
    """Why no shipped weights fit `model`: the [model] keys in which those of its base differ from it."""
    hints = []
    for path, saved in _shipped(weights_dir):
        if saved.base == model.base:
            keys = differing_keys(dataclasses.asdict(saved), dataclasses.asdict(model))
            hints.append(f"{path.name} has " + ", ".join(f"model.{k} = {getattr(saved, k)!r}" for k in keys))
    return f" ({'; '.join(hints)})" if hints else ""


def train_dir(cfg: Config, stage: str) -> Path:
    """workdir/train/<stage>, or <stage>-oidn for a refiner, then -noise for model.noise_input: the models
    train side by side."""
    name = stage if cfg.model.base == "noisy" else f"{stage}-{cfg.model.base}"
    return cfg.workdir_path("train") / (f"{name}-noise" if cfg.model.noise_input else name)


def default_weights(cfg: Config) -> Path:
    """What denoising and evaluation use when no weights are named: this config's fine-tuned run, else
    its pretrained run, else the shipped weights for its [model]."""
    for stage in ("finetune", "pretrain"):
        candidate = train_dir(cfg, stage) / WEIGHTS_NAME
        if candidate.is_file():
            return candidate
    shipped = shipped_weights(cfg.model)
    if shipped is None:
        raise StageError(
            f"no trained weights under {cfg.workdir_path('train')} and none shipped for this "
            "[model] config: run `admc-pipe train` or pass --weights"
        )
    return shipped


def load_model(
    cfg: Config,
    weights: Path | None,
    options: DenoiserOptions = DenoiserOptions(device="auto"),
    oidn_blend: bool = True,
) -> FullImageDenoiser:
    """The trained denoiser from `weights` (default: `default_weights`), run as `options` say (its device may
    also be "auto": a CUDA GPU where torch sees one, else the CPU): the engine, ensemble, dark pass and
    keeping of resolved detail (model/inference/options.py), blended with OIDN where the weights ship a
    blend and `oidn_blend` (train.oidn_blend)."""
    return load_denoiser(
        weights or default_weights(cfg), replace(options, device=resolve_device(options.device)), oidn_blend=oidn_blend
    )
