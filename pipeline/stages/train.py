"""`admc-pipe train`: build (or reuse) the patch store, then pretrain or fine-tune both branches."""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

from admc.errors import ConfigError, StageError
from admc.model.precision import resolve_device
from admc.model.training import distributed
from admc.model.training.distributed import check_world
from admc.model.training.trainer import TrainResult, check_fresh_start, train
from admc.pipeline.config import Config
from admc.pipeline.render import backends as render
from admc.pipeline.stages.corpus import corpus_splits
from admc.pipeline.stages.dataset import build_dataset
from admc.pipeline.weights import shipped_mismatch, shipped_weights, train_dir
from admc.stores.checkpoints import CHECKPOINT_NAME, WEIGHTS_NAME, load_checkpoint, read_networks


def run_training(
    cfg: Config, stage: str, init_from: Path | None = None, restart: bool = False, progress: bool = True, nproc: int = 1
) -> TrainResult:
    """Pretrain on the config's corpus, or fine-tune on it from `init_from` (default: the shipped weights).

    Like every stage, training is resumable: a run whose checkpoint exists continues from it (and does
    nothing once complete); a changed architecture or store is refused by the trainer. `restart`
    discards the existing run first. `nproc` > 1 trains in that many processes on this machine; under
    torchrun each process is one rank already, and rank 0 alone prepares the run and the store.
    """
    device = resolve_device(cfg.train.device)
    ranks = distributed.join_from_env(device)
    if nproc > 1 and ranks.world > 1:
        raise StageError(
            f"--nproc {nproc}: this process is already rank {ranks.rank} of {ranks.world} (torchrun); leave --nproc out"
        )
    check_world(cfg.train, cfg.model, max(nproc, ranks.world))
    prepared = _prepare(cfg, stage, init_from, restart, progress) if ranks.lead else None
    store, init_from, resume, notes = distributed.share(prepared)
    kwargs = dict(
        store_path=store,
        out_dir=train_dir(cfg, stage),
        settings=cfg.train,
        model=cfg.model,
        stage=stage,
        init_from=None if resume else init_from,
        resume=resume,
        progress=progress,
    )
    try:
        result = distributed.launch(nproc, device, train, kwargs) if nproc > 1 else train(**kwargs)
    except distributed.RankFailed as exc:
        raise StageError(f"{exc}\n{interrupted_note(cfg, stage)}") from None
    result.notes[:0] = notes
    return result


def _prepare(
    cfg: Config, stage: str, init_from: Path | None, restart: bool, progress: bool
) -> tuple[Path, Path | None, bool, list[str]]:
    """(patch store, init weights, resume?, notes): restart, find the weights, build the store."""
    out_dir = train_dir(cfg, stage)
    if restart and out_dir.exists():
        shutil.rmtree(out_dir)
    resume = (out_dir / CHECKPOINT_NAME).is_file()
    if not resume:
        check_fresh_start(out_dir)  # before the dataset is built, not after
    if stage == "finetune" and init_from is None and not resume:
        init_from = shipped_weights(cfg.model)
        if init_from is None:
            raise StageError(
                "finetune needs pretrained weights: pass --init CHECKPOINT (e.g. "
                f"{train_dir(cfg, 'pretrain') / WEIGHTS_NAME}); no shipped weights in weights/ "
                f"match this [model] config{shipped_mismatch(cfg.model)}"
            )
    if init_from is not None and not Path(init_from).is_file():
        raise StageError(f"{init_from}: no such checkpoint or weights file")
    check_splits(cfg)
    if init_from is not None and not resume:
        read_networks(init_from)  # a damaged or foreign file is refused before the dataset is built
    dataset = build_dataset(cfg, progress=progress)  # cached: nothing to do once the store is built
    return dataset.store, init_from, resume, dataset.notes


def check_splits(cfg: Config) -> None:
    """Refuse, before anything is rendered, a tile.split that leaves training (or validation, with
    train.val_every > 0 and tile.val_set = "split") without a single scene of the corpus."""
    specs = render.corpus(cfg)
    if not specs:
        raise ConfigError(
            "the corpus is empty: corpus.n_scenes = 0 and no scene in corpus.xml_dirs or corpus.blend_dirs; "
            "name your folder of frames, e.g. --set 'corpus.xml_dirs=[\"/path/to/frames\"]'"
        )
    counts = Counter(corpus_splits(cfg, specs).values())
    corpus = f"the {len(specs)}-scene corpus (tile.split = {list(cfg.tile.split)}, tile.seed = {cfg.tile.seed})"
    if not counts["train"]:
        raise ConfigError(
            f"config key 'tile.split': no scene of {corpus} falls in the train split; "
            "give train a larger share or add scenes"
        )
    if cfg.train.val_every and not counts["val"] and cfg.tile.val_set == "split":
        raise ConfigError(
            f"config key 'tile.split': no scene of {corpus} falls in the val split, which "
            f"train.val_every = {cfg.train.val_every} validates on; give val a share, add scenes, "
            "or set train.val_every = 0"
        )


def interrupted_note(cfg: Config, stage: str) -> str:
    """What an interrupted `train` kept. Read from the checkpoint on disk, so it is true wherever the run
    stopped (a checkpoint is published by rename: an interrupted save leaves the previous one whole)."""
    path = train_dir(cfg, stage) / CHECKPOINT_NAME
    if not path.is_file():
        return (
            f"interrupted: no checkpoint written yet (one is written every train.checkpoint_every = "
            f"{cfg.train.checkpoint_every} steps to {path}); run the same command to start over"
        )
    step = load_checkpoint(path)["step"]
    return (
        f"interrupted: checkpoint {path} holds step {step} (steps after it are not saved); run the same "
        f"command to resume from it"
    )
