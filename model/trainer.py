"""`pretrain` and `finetune`: train both branches' CFM generators and WGAN-GP critics on a patch store.

One global step advances every branch once (see TrainSettings.phase for the L1 warm-up, critic
pretraining and adversarial phases). The checkpoint holds everything the next step depends on
(weights, optimisers, schedulers, RNG states, data-stream positions), so `resume=True` continues
bit-identically on the CPU. The store's transform spec must equal the one the weights were trained
on (checkpoint, init weights, or this code's for a fresh pretrain); a resumed run also needs the very
same store (fingerprint).
"""
from __future__ import annotations

import dataclasses
import logging
import random
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from admc.errors import AdmcError, DeviceError, TrainingError
from admc.stores.checkpoints import export_weights, load_checkpoint, read_networks, save_checkpoint
from admc.stores.patches import PatchReader, PatchStoreError, fingerprint as store_fingerprint

from .branch import BranchTrainer
from .data import branch_seed, load_rows, train_loader
from .metrics_log import MetricsLog
from .selection import SELECTION_METRIC, BestNetworks
from .precision import precision_name
from .settings import STAGES, ModelSettings, TrainSettings
from .transforms import transform_spec
from .validation import validate

CHECKPOINT_NAME = "checkpoint.pt"
WEIGHTS_NAME = "weights-fp16.pt"
# Settings a resumed run may change without changing what it computes.
# precision: weights, Adam states and losses stay float32 under bf16 autocast, so a run resumed in the
# other precision continues correctly, just not bit-identically (said in a note), as after a device change.
RESUMABLE_CHANGES = ("steps", "val_every", "val_patches", "checkpoint_every", "log_every", "num_workers",
                     "threads", "device", "precision", "max_bad_steps")
log = logging.getLogger("admc.train")


class TrainingDiverged(AdmcError, RuntimeError):
    """Too many consecutive steps had non-finite losses or gradients."""


@dataclass
class TrainResult:
    out_dir: Path
    checkpoint: Path
    weights: Path
    step: int
    branches: list[str]
    skipped_branches: list[str]
    bad_steps: dict[str, int]
    last_losses: dict[str, dict[str, float]]
    validation: dict[str, dict[str, float]]
    notes: list[str] = field(default_factory=list)
    selected: dict[str, dict] = field(default_factory=dict)  # branch -> {"step", "val_relmse"} of the shipped weights


def resolve_device(name: str) -> torch.device:
    """auto | cpu | cuda | cuda:N as a torch device this machine has; DeviceError naming the value otherwise."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise DeviceError(f"device {name!r}: not a device admc runs on; use auto, cpu, cuda or cuda:N")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError(f"device {name!r}: requested, but torch sees no CUDA device on this machine")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise DeviceError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device


def _rng_state() -> dict:
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    state = {"python": random.getstate(), "torch": torch.get_rng_state(),
             "numpy": (kind, keys.tolist(), pos, has_gauss, cached)}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    torch.set_rng_state(state["torch"])
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, np.array(keys, dtype=np.uint32), pos, has_gauss, cached))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _check_resumable(checkpoint: dict, path: Path, settings: TrainSettings, model: ModelSettings, stage: str,
                     fingerprint: str) -> None:
    if checkpoint["stage"] != stage:
        raise TrainingError(f"{path}: is a {checkpoint['stage']!r} checkpoint, cannot resume it as {stage!r}")
    saved = dataclasses.asdict(ModelSettings.from_saved(checkpoint["model"]))
    if saved != dataclasses.asdict(model):
        diff = [k for k, v in dataclasses.asdict(model).items() if saved[k] != v]
        raise TrainingError(f"{path}: model settings differ from the checkpoint's in {diff}")
    saved, now = checkpoint["settings"], dataclasses.asdict(settings)
    diff = [k for k in now if k not in RESUMABLE_CHANGES and saved.get(k) != now[k]]
    if diff:
        raise TrainingError(f"{path}: train settings {diff} differ from the checkpoint's; an exact resume allows "
                            f"changing only {list(RESUMABLE_CHANGES)}")
    if checkpoint["store"]["fingerprint"] != fingerprint:
        raise TrainingError(f"{path}: the patch store changed since this checkpoint (scenes or attributes differ); "
                            "resume needs the same data: start a 'finetune' from the checkpoint instead")


def _say_precision_change(checkpoint: dict, precision: str, say) -> None:
    """Note a resume in another precision than the checkpoint's steps ran in (older checkpoints do not
    say which)."""
    before = checkpoint.get("precision")
    if before is not None and before != precision:
        say(f"the checkpoint's steps ran in {before}, this run continues in {precision}: training goes on "
            f"from the same state, but not bit-identically to an uninterrupted {before} run")


def _load_init(init_from: Path | None, model: ModelSettings) -> tuple[dict, dict, str]:
    """(branch -> {"generator", "critic"}, transform spec, description) from a checkpoint or fp16 weights."""
    if init_from is None:
        raise TrainingError("stage 'finetune' needs init_from (a checkpoint or exported weights)")
    init_from = Path(init_from)
    nets, saved_model, transform = read_networks(init_from)
    saved = dataclasses.asdict(ModelSettings.from_saved(saved_model))
    if saved != dataclasses.asdict(model):
        diff = [k for k, v in dataclasses.asdict(model).items() if saved[k] != v]
        raise TrainingError(f"{init_from}: its model settings differ from the configured ones in {diff}")
    return nets, transform, str(init_from)


def _open_reader(store: Path, split: str, transform: dict, branch: str, source: str) -> PatchReader:
    try:
        return PatchReader(store, split, expect_transform=transform, branch=branch)
    except PatchStoreError as exc:
        raise PatchStoreError(f"refused for {source}: {exc}") from None


class _Averages:
    """Running means of the logged losses since the last log line."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)

    def add(self, prefix: str, values: dict[str, float]) -> None:
        for k, v in values.items():
            self.sums[f"{prefix}/{k}"] += v
            self.counts[f"{prefix}/{k}"] += 1

    def pop(self) -> dict[str, float]:
        out = {k: self.sums[k] / self.counts[k] for k in self.sums}
        self.sums.clear()
        self.counts.clear()
        return out


def train(store_path: str | Path, out_dir: str | Path, settings: TrainSettings, model: ModelSettings,
          stage: str = "pretrain", init_from: str | Path | None = None, resume: bool = False,
          progress: bool = True) -> TrainResult:
    """Train (or resume training) both branches; writes checkpoint.pt, weights-fp16.pt, metrics.csv and
    TensorBoard events to `out_dir`. Raises TrainingDiverged after max_bad_steps consecutive
    non-finite steps (the last checkpoint on disk is then the last one written before the streak)."""
    settings.check()
    model.check()
    if stage not in STAGES:
        raise TrainingError(f"stage: {stage!r} is not one of {STAGES}")
    store, out_dir = Path(store_path), Path(out_dir)
    checkpoint_path, weights_path = out_dir / CHECKPOINT_NAME, out_dir / WEIGHTS_NAME
    notes: list[str] = []

    def say(message: str) -> None:
        notes.append(message)
        log.info(message)
        if progress:
            tqdm.write(message)

    device = resolve_device(settings.device)
    if device.type == "cpu" and settings.threads:
        torch.set_num_threads(settings.threads)
    fingerprint = store_fingerprint(store) if (store / "zarr.json").is_file() else None
    checkpoint, init_nets = None, None
    if resume:
        checkpoint = load_checkpoint(checkpoint_path)
        transform, source = checkpoint["transform"], f"checkpoint {checkpoint_path}"
    else:
        if checkpoint_path.exists():
            raise TrainingError(f"{checkpoint_path} exists: pass resume=True to continue that run, "
                                "or use another out_dir")
        if stage == "finetune":
            init_nets, transform, source = _load_init(init_from, model)
            source = f"init weights {source}"
        elif init_from is not None:
            raise TrainingError("init_from: only stage 'finetune' starts from existing weights")
        else:
            transform, source = transform_spec(), "this code's transform spec"

    readers: dict[str, PatchReader] = {}
    skipped: list[str] = []
    for branch in settings.branches:
        reader = _open_reader(store, "train", transform, branch, source)
        if len(reader) == 0 and branch == "specular":
            skipped.append(branch)
            say(f"{store}: no specular patches in the train split; the specular branch is not trained")
            continue
        if len(reader) == 0:
            raise PatchStoreError(f"{store}: the train split has no {branch} patches")
        readers[branch] = reader
    if not readers:
        raise PatchStoreError(f"{store}: nothing to train for branches {list(settings.branches)}")
    if resume:
        _check_resumable(checkpoint, checkpoint_path, settings, model, stage, fingerprint)
    patch_size = int(next(iter(readers.values())).attrs["patch_size"])

    val: dict[str, dict] = {}
    if settings.val_every:
        for branch in readers:
            val_reader = _open_reader(store, "val", transform, branch, source)
            if len(val_reader) == 0 and branch == "specular":
                say(f"{store}: no specular patches in the val split; specular is not validated")
                continue
            if len(val_reader) == 0:
                raise PatchStoreError(f"{store}: the val split has no {branch} patches (needed as val_every > 0)")
            val[branch] = load_rows(val_reader, settings.val_patches)

    _seed_everything(settings.seed)
    trainers = {b: BranchTrainer(b, model, settings, patch_size, device) for b in readers}
    precision = precision_name(next(iter(trainers.values())).dtype)
    start = 0
    if checkpoint is not None:
        for b, trainer in trainers.items():
            if b not in checkpoint["branches"]:
                raise TrainingError(f"{checkpoint_path}: has no {b} branch but the store and settings train it")
            trainer.load_state_dict(checkpoint["branches"][b], str(checkpoint_path))
        _set_rng_state(checkpoint["rng"])
        start = int(checkpoint["step"])
        say(f"resuming {stage} from {checkpoint_path} at step {start}")
        _say_precision_change(checkpoint, precision, say)
    elif init_nets is not None:
        for b, trainer in trainers.items():
            if b not in init_nets:
                raise TrainingError(f"{init_from}: has no {b} branch to fine-tune")
            trainer.load_networks(init_nets[b]["generator"], init_nets[b]["critic"], str(init_from))
    best = BestNetworks()
    if checkpoint is not None:
        best.load_state_dict(checkpoint.get("best", {}))

    def state(step: int) -> dict:
        return {"stage": stage, "step": step, "settings": dataclasses.asdict(settings), "precision": precision,
                "model": dataclasses.asdict(model), "transform": transform,
                "store": {"path": str(store), "fingerprint": fingerprint, "patch_size": patch_size},
                "init_from": str(init_from) if init_from is not None else None,
                "branches": {b: t.state_dict() for b, t in trainers.items()}, "best": best.state_dict(),
                "rng": _rng_state()}

    pin = device.type == "cuda"
    streams = {b: iter(train_loader(readers[b], settings.batch_size, branch_seed(settings.seed, b),
                                    trainers[b].batches, settings.num_workers, pin)) for b in trainers}
    metrics = MetricsLog(out_dir, resume_step=start if resume else None)
    averages, last_losses, validation = _Averages(), {}, {}

    def validate_all(step: int) -> None:
        for b, rows in val.items():
            validation[b] = validate(trainers[b].generator, rows, b, settings.batch_size, device, trainers[b].dtype)
            metrics.log(step, {f"{b}/val_{k}": v for k, v in validation[b].items()})
            best.offer(b, step, validation[b][SELECTION_METRIC], trainers[b].generator, trainers[b].critic)

    last_saved = start if resume else None
    # A live bar only on a terminal; in a log file or CI output its carriage-return redraws are noise,
    # so there the logged averages go out as one plain line every log_every steps instead.
    live = progress and sys.stderr.isatty()
    bar = tqdm(total=settings.steps, initial=start, disable=not live, desc=stage, dynamic_ncols=True)
    window_start, window_patches = time.perf_counter(), 0
    try:
        if start == 0 and settings.val_every:
            validate_all(0)  # the starting weights: what the run must beat to ship anything else
        for step in range(start, settings.steps):
            for b, trainer in trainers.items():
                batches = [next(streams[b]) for _ in range(trainer.batches_per_step(step))]
                ok, losses = trainer.step(step, batches)
                window_patches += len(batches) * settings.batch_size
                if ok:
                    averages.add(b, losses)
                    last_losses[b] = losses
                    continue
                say(f"step {step}: {b} skipped, non-finite batch, loss or gradient "
                    f"({trainer.bad_consecutive} in a row, {trainer.bad_total} in all)")
                if trainer.bad_consecutive >= settings.max_bad_steps:
                    kept = f"step {last_saved}" if last_saved is not None else "none written"
                    raise TrainingDiverged(
                        f"{b}: {trainer.bad_consecutive} consecutive steps with non-finite batches, losses or "
                        f"gradients (steps {step - trainer.bad_consecutive + 1}..{step}); stopped. Last good "
                        f"checkpoint: {checkpoint_path} ({kept})")
            done = step + 1
            bar.update(1)
            if done % settings.log_every == 0 or done == settings.steps:
                elapsed = time.perf_counter() - window_start
                values = averages.pop()
                values["patches_per_s"] = window_patches / max(elapsed, 1e-9)
                for b, trainer in trainers.items():
                    values.update({f"{b}/{k}": v for k, v in trainer.learning_rates().items()})
                    values[f"{b}/bad_steps"] = trainer.bad_total
                values["phase"] = ("l1", "critic", "adversarial").index(settings.phase(step))
                metrics.log(done, values)
                bar.set_postfix(_postfix(values), refresh=False)
                if progress and not live:
                    line = " ".join(f"{k}={v}" for k, v in _postfix(values).items())
                    print(f"{stage} step {done}/{settings.steps}: {line}", file=sys.stderr, flush=True)
                window_start, window_patches = time.perf_counter(), 0
            if settings.val_every and (done % settings.val_every == 0 or done == settings.steps):
                validate_all(done)
            streak = any(t.bad_consecutive for t in trainers.values())
            if done == settings.steps or (done % settings.checkpoint_every == 0 and not streak):
                save_checkpoint(checkpoint_path, state(done))
                last_saved = done
    finally:
        bar.close()
        metrics.close()
        del streams

    last_step = max(start, settings.steps)
    selected, selection_notes = best.summary(last_step, {b: v[SELECTION_METRIC] for b, v in validation.items()})
    notes.extend(selection_notes)  # said once, with the result, where the caller reports the weights file
    for note in selection_notes:
        log.info(note)
    export_weights(weights_path, {b: best.networks(b, t.generator, t.critic) for b, t in trainers.items()},
                   {"model": dataclasses.asdict(model), "transform": transform, "patch_size": patch_size,
                    "stage": stage, "step": last_step, "selected": selected, "store_fingerprint": fingerprint,
                    "precision": precision})
    return TrainResult(out_dir=out_dir, checkpoint=checkpoint_path, weights=weights_path,
                       step=last_step, branches=list(trainers), skipped_branches=skipped,
                       bad_steps={b: t.bad_total for b, t in trainers.items()}, last_losses=last_losses,
                       validation=validation, notes=notes, selected=selected)


def _postfix(values: dict[str, float]) -> dict[str, str]:
    short = {"l1": "l1", "wasserstein": "W", "gp": "gp"}
    out = {}
    for tag, value in values.items():
        branch, _, key = tag.partition("/")
        if key in short:
            out[f"{branch[0]}.{short[key]}"] = f"{value:.3g}"
    out["p/s"] = f"{values['patches_per_s']:.1f}"
    return out
