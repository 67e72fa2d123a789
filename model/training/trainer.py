"""`pretrain` and `finetune`: train both branches' CFM generators and WGAN-GP critics on a patch store.

One global step advances every branch once (see TrainSettings.phase for the L1 warm-up, critic
pretraining and adversarial phases). The checkpoint holds everything the next step depends on
(weights, optimisers, schedulers, RNG states, data-stream positions), so `resume=True` continues
bit-identically on the CPU. The store's transform spec must equal the one the weights were trained
on (checkpoint, init weights, or this code's for a fresh pretrain); a resumed run also needs the very
same store (fingerprint).

Under data-parallel training (several processes, see distributed.py) every rank runs this same code on
its shard of each global batch of train.batch_size; rank 0 alone validates, selects, writes and speaks.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from admc.errors import AdmcError, TrainingError
from admc.stores import patches
from admc.stores.checkpoints import (
    CHECKPOINT_NAME,
    OIDN_BLEND,
    WEIGHTS_NAME,
    export_weights,
    load_checkpoint,
    read_oidn_networks,
    save_checkpoint,
)
from admc.stores.patches import PatchReader, PatchStoreError

from ..nets.settings import ModelSettings
from ..precision import precision_name, resolve_device
from ..transforms import transform_spec
from .branch import BranchTrainer
from .clock import Clock
from .data import branch_seed, load_rows, train_loader
from .distributed import RankFailed, Ranks, agree, broadcast_modules, check_world, current, rank_device
from .metrics_log import MetricsLog
from .oidn_partner import METRIC_LABELS, Partner, finetune_partner, start_partner
from .progress import ProgressWindow
from .resume import check_resumable, load_init, rng_state, say_precision_change, seed_everything, set_rng_state
from .selection import BestNetworks, selection_values
from ..train_settings import STAGES, TrainSettings
from .validation import baseline_scores, best_blend, validate

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
    last_losses: dict[str, dict[str, float]]
    validation: dict[str, dict[str, float]]
    notes: list[str] = field(default_factory=list)  # what the run has to say and has not shown yet
    selected: dict[str, dict] = field(default_factory=dict)  # branch -> {"step", selection.selected_key} shipped
    rank: int = 0  # the process that returns it; only rank 0's speaks for the run


def _open_reader(run: _Run, split: str, transform: dict, branch: str, source: str) -> PatchReader:
    """The rows of a split and branch, with their OIDN bases for a refiner (model.base "oidn" or "oidn-fast",
    stored at its qualities) and their noise maps in the features for model.noise_input."""
    try:
        return PatchReader(
            run.store,
            split,
            expect_transform=transform,
            branch=branch,
            base=None if run.model.base == "noisy" else run.model.base,
            noise=run.model.noise_input,
        )
    except PatchStoreError as exc:
        raise PatchStoreError(f"refused for {source}: {exc}") from None


def train(
    store_path: str | Path,
    out_dir: str | Path,
    settings: TrainSettings,
    model: ModelSettings,
    stage: str = "pretrain",
    init_from: str | Path | None = None,
    resume: bool = False,
    progress: bool = True,
) -> TrainResult:
    """Train (or resume training) both branches; writes checkpoint.pt, weights-fp16.pt, metrics.csv and
    TensorBoard events to `out_dir`. Raises TrainingDiverged after max_bad_steps consecutive
    non-finite steps (the last checkpoint on disk is then the last one written before the streak)."""
    settings.check()
    model.check()
    if stage not in STAGES:
        raise TrainingError(f"stage: {stage!r} is not one of {STAGES}")
    check_world(settings, model, current().world)
    run = _Run(Path(store_path), Path(out_dir), settings, model, stage, init_from, progress)
    checkpoint, init_nets, transform, source = _starting_point(run, resume)
    readers = _open_train(run, transform, source)
    if resume:
        check_resumable(checkpoint, run.checkpoint_path, settings, model, stage, run.fingerprint)
    run.transform = transform
    run.patch_size = int(next(iter(readers.values())).attrs["patch_size"])
    val = _load_val(run, readers, transform, source)
    seed_everything(settings.seed)
    run.trainers = {b: BranchTrainer(b, model, settings, run.patch_size, run.device) for b in readers}
    run.precision = precision_name(next(iter(run.trainers.values())).dtype)
    start = _restore(run, checkpoint, init_nets)
    for trainer in run.trainers.values():
        broadcast_modules(trainer.generator, trainer.critic, *[m for m in [trainer.average] if m is not None])
    if settings.oidn_minutes > 0 and model.base == "noisy":
        _fine_tune_oidn(run, readers, val, checkpoint)
    elif settings.oidn_minutes > 0:
        run.say(
            f"train.oidn_minutes: skipped for a refiner (model.base = {model.base!r}): it refines OIDN's own "
            "output; OIDN's fine-tune is the partner of admc's blend"
        )
    _loop(run, readers, val, start, resume)
    return _finish(run, start)


@dataclass
class _Run:
    """What every part of one training run shares: its inputs, networks, logs and what it has said."""

    store: Path
    out_dir: Path
    settings: TrainSettings
    model: ModelSettings
    stage: str
    init_from: str | Path | None
    progress: bool
    notes: list[str] = field(default_factory=list)
    trainers: dict[str, BranchTrainer] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)
    best: BestNetworks = field(init=False)
    validation: dict[str, dict[str, float]] = field(default_factory=dict)
    baselines: dict[str, dict[str, float]] = field(default_factory=dict)  # branch -> the val scores of its input
    start_scores: dict[str, dict[str, float]] = field(default_factory=dict)  # branch -> its first validation
    blends: dict[str, dict[int, float]] = field(default_factory=dict)  # branch -> step -> its best OIDN blend share
    last_losses: dict[str, dict[str, float]] = field(default_factory=dict)
    transform: dict | None = None
    patch_size: int = 0
    precision: str = ""
    metrics: MetricsLog | None = None
    step: int = 0  # the last step run (or restored)
    partner: Partner | None = None  # OIDN's networks fine-tuned first (train.oidn_minutes)

    def __post_init__(self) -> None:
        self.checkpoint_path = self.out_dir / CHECKPOINT_NAME
        self.weights_path = self.out_dir / WEIGHTS_NAME
        self.ranks: Ranks = current()
        self.progress = self.progress and self.ranks.lead  # the other ranks stay silent
        self.device = rank_device(resolve_device(self.settings.device), self.ranks)
        if self.device.type == "cpu" and (self.settings.threads or self.ranks.local_world > 1):
            # processes sharing the CPU share its cores (torch would give each all of them)
            share = max(1, (os.cpu_count() or 1) // self.ranks.local_world)
            torch.set_num_threads(self.settings.threads or share)
        self.fingerprint = patches.fingerprint(self.store) if patches.exists(self.store) else None
        self.best = BestNetworks(self.settings.select_z, self.settings.select_metric)
        self.last_selection: dict[str, float] = {}  # branch -> the last validation's mean selection value
        self.clock = Clock(self.settings.minutes)

    def say(self, message: str) -> None:
        """Show a note now under the progress bar, or (without one) keep it for the caller to report."""
        log.info(message)
        if self.progress:
            tqdm.write(message)
        else:
            self.notes.append(message)

    def show(self, message: str) -> None:
        """A progress line (validation against the start and OIDN): under the bar, or on stderr without one."""
        log.info(message)
        if self.progress:
            tqdm.write(message, file=sys.stderr)

    def state(self, step: int) -> dict:
        """Everything the next step depends on: the checkpoint's content."""
        return {
            "stage": self.stage,
            "step": step,
            "settings": dataclasses.asdict(self.settings),
            "precision": self.precision,
            "model": dataclasses.asdict(self.model),
            "transform": self.transform,
            "store": {"path": str(self.store), "fingerprint": self.fingerprint, "patch_size": self.patch_size},
            "init_from": str(self.init_from) if self.init_from is not None else None,
            "branches": {b: t.state_dict() for b, t in self.trainers.items()},
            "best": self.best.state_dict(),
            "rng": rng_state(),
            "seconds": self.clock.seconds(),
            "start_scores": self.start_scores,
            "blends": self.blends,
            "partner": self.partner.state_dict() if self.partner else None,
        }


def check_fresh_start(out_dir: Path) -> None:
    """Refuse to start a run from step 0 in `out_dir` over an earlier run's checkpoint or finished weights:
    a deleted checkpoint must not let a fresh start silently replace the weights a run shipped."""
    checkpoint, weights = Path(out_dir) / CHECKPOINT_NAME, Path(out_dir) / WEIGHTS_NAME
    if checkpoint.exists():
        raise TrainingError(f"{checkpoint} exists: pass resume=True to continue that run, or use another out_dir")
    if weights.exists():
        raise TrainingError(
            f"{weights}: holds the finished weights of an earlier run, whose {CHECKPOINT_NAME} is "
            "gone, so it cannot resume; a new run from step 0 would replace them: move them away "
            "first, or pass --restart to discard that run"
        )


def _starting_point(run: _Run, resume: bool) -> tuple[dict | None, dict | None, dict, str]:
    """(checkpoint, init networks, transform spec, where the spec came from) for a resumed, fine-tuned
    or fresh run; refuses a fresh run over an existing checkpoint."""
    if resume:
        checkpoint = load_checkpoint(run.checkpoint_path)
        return checkpoint, None, checkpoint["transform"], f"checkpoint {run.checkpoint_path}"
    check_fresh_start(run.out_dir)
    if run.stage == "finetune":
        init_nets, transform, source = load_init(run.init_from, run.model)
        if source != str(run.init_from):  # what load_init did to the weights (the noise input added)
            run.say(f"finetune starts from {source}")
        return None, init_nets, transform, f"init weights {source}"
    if run.init_from is not None:
        raise TrainingError("init_from: only stage 'finetune' starts from existing weights")
    return None, None, transform_spec(), "this code's transform spec"


def _open_train(run: _Run, transform: dict, source: str) -> dict[str, PatchReader]:
    """The train readers of the branches that have patches."""
    store, settings = run.store, run.settings
    readers: dict[str, PatchReader] = {}
    for branch in settings.branches:
        reader = _open_reader(run, "train", transform, branch, source)
        if len(reader) == 0 and branch == "specular":
            run.skipped.append(branch)
            run.say(f"{store}: no specular patches in the train split; the specular branch is not trained")
            continue
        if len(reader) == 0:
            raise PatchStoreError(f"{store}: the train split has no {branch} patches")
        readers[branch] = reader
    if not readers:
        raise PatchStoreError(f"{store}: nothing to train for branches {list(settings.branches)}")
    return readers


def _load_val(run: _Run, readers: dict[str, PatchReader], transform: dict, source: str) -> dict[str, dict]:
    """The fixed val rows of every trained branch that has val patches (none when val_every = 0), with
    OIDN's output for the same rows ("oidn") where the store holds it: what validation compares with."""
    store, settings = run.store, run.settings
    val: dict[str, dict] = {}
    if settings.val_every:
        for branch in readers:
            val_reader = _open_reader(run, "val", transform, branch, source)
            if len(val_reader) == 0 and branch == "specular":
                run.say(f"{store}: no specular patches in the val split; specular is not validated")
                continue
            if len(val_reader) == 0:
                raise PatchStoreError(f"{store}: the val split has no {branch} patches (needed as val_every > 0)")
            val[branch] = load_rows(val_reader, settings.val_patches)
            oidn = _oidn_rows(run, branch, transform, settings.val_patches)
            if oidn is not None:
                val[branch]["oidn"] = oidn
    return val


def _oidn_rows(run: _Run, branch: str, transform: dict, n: int):
    """OIDN's output (the store's `high` bases) for the val rows, or None where the store has none."""
    if run.model.base == "oidn":
        return None  # the refiner's own base is that output: validation reports it as base_*
    try:
        reader = PatchReader(run.store, "val", expect_transform=transform, branch=branch, base="oidn")
    except PatchStoreError:
        return None
    return load_rows(reader, n)["base"]


def _restore(run: _Run, checkpoint: dict | None, init_nets: dict | None) -> int:
    """Load the checkpoint's full state (returns its step) or the init networks (returns 0)."""
    if checkpoint is not None:
        for b, trainer in run.trainers.items():
            if b not in checkpoint["branches"]:
                raise TrainingError(f"{run.checkpoint_path}: has no {b} branch but the store and settings train it")
            trainer.load_state_dict(checkpoint["branches"][b], str(run.checkpoint_path))
        set_rng_state(checkpoint["rng"])
        run.best.load_state_dict(checkpoint.get("best", {}))
        run.start_scores.update(checkpoint.get("start_scores", {}))
        run.blends.update(checkpoint.get("blends", {}))
        start = int(checkpoint["step"])
        run.clock.before = float(checkpoint.get("seconds", 0.0))
        run.say(f"resuming {run.stage} from {run.checkpoint_path} at step {start}")
        say_precision_change(checkpoint, run.precision, run.say)
        return start
    if init_nets is not None:
        for b, trainer in run.trainers.items():
            if b not in init_nets:
                raise TrainingError(f"{run.init_from}: has no {b} branch to fine-tune")
            trainer.load_networks(init_nets[b]["generator"], init_nets[b]["critic"], str(run.init_from))
    return 0


def _fine_tune_oidn(run: _Run, readers: dict[str, PatchReader], val: dict[str, dict], checkpoint: dict | None) -> None:
    """The partner phase (oidn_partner.py), before admc's steps and outside train.minutes; its state rides in
    the checkpoint at step 0, so an interrupted phase resumes."""
    init = read_oidn_networks(run.init_from) if run.init_from is not None else None
    raw = [b for b, r in readers.items() if r.holds_raw_references]  # beside cleaned targets: oidn_partner.CANDIDATES
    run.partner = start_partner(list(readers), run.settings, init, run.device, raw)
    if checkpoint is not None and checkpoint.get("partner"):
        run.partner.load_state_dict(checkpoint["partner"])
    if not run.partner.done:
        run.say(f"fine-tuning OIDN's networks first: train.oidn_minutes = {run.settings.oidn_minutes:g}")

    def save() -> None:
        if run.ranks.lead:
            save_checkpoint(run.checkpoint_path, {**run.state(0), "seconds": 0.0})

    finetune_partner(run.partner, run.settings, readers, val, run.device, save, run.show, run.progress)
    run.clock = Clock(run.settings.minutes, before=run.clock.before)  # admc's budget starts now


def _validate_all(run: _Run, val: dict[str, dict], step: int) -> None:
    """Validate every branch, log it, show it against the start and OIDN, and offer its networks to the
    selection of the shipped weights."""
    for b, rows in val.items():
        trainer = run.trainers[b]
        scores, per_patch, output = validate(
            trainer.shipped_generator, rows, b, run.settings.batch_size, run.device, trainer.dtype
        )
        if b not in run.baselines:
            run.baselines[b] = baseline_scores(rows, b)
        run.start_scores.setdefault(b, scores)  # step 0's (a checkpoint carries them over a resume)
        run.validation[b] = {**scores, **run.baselines[b], **_ratios(scores, run.start_scores[b], run.baselines[b])}
        if run.settings.oidn_blend and "oidn" in rows:
            share, blended = best_blend(output, rows, b, run.partner.val_outputs.get(b) if run.partner else None)
            run.blends.setdefault(b, {})[step] = share
            run.validation[b].update(
                blend_partner=float(run.partner is not None),
                blend_share=share,
                blend_relmse=blended,
                blend_relmse_vs_oidn=blended / max(run.baselines[b]["oidn_relmse"], 1e-12),
            )
        run.metrics.log(step, {f"{b}/val_{k}": v for k, v in run.validation[b].items()})
        run.show(f"step {step} {b} validation: " + _comparison(run.validation[b]))
        values = selection_values(run.settings.select_metric, per_patch, run.validation[b])
        run.last_selection[b] = float(values.mean())
        guard = step == 0 and run.init_from is not None  # fine-tuning: ship nothing that is not proven better
        run.best.offer(b, step, values, trainer.shipped_generator, trainer.critic, guard=guard)


def _ratios(scores: dict[str, float], start: dict[str, float], baselines: dict[str, float]) -> dict[str, float]:
    """Each error as a multiple of the starting weights' ("_vs_start") and of OIDN's on the same patches
    ("_vs_oidn": the store's OIDN output, or a refiner's OIDN base)."""
    out = {}
    for k in ("relmse", "one_minus_ssim"):
        out[f"{k}_vs_start"] = scores[k] / max(start[k], 1e-12)
        oidn = baselines.get(f"oidn_{k}", baselines.get(f"base_{k}"))
        if oidn is not None:
            out[f"{k}_vs_oidn"] = scores[k] / max(oidn, 1e-12)
    return out


def _comparison(validation: dict[str, float]) -> str:
    """relMSE and 1-SSIM with their multiples of the start and of OIDN, in one line."""
    parts = []
    for k, label in (("relmse", "relMSE"), ("one_minus_ssim", "1-SSIM")):
        vs = [f"{validation[f'{k}_vs_start']:.3f}x the start"]
        if f"{k}_vs_oidn" in validation:
            vs.append(f"{validation[f'{k}_vs_oidn']:.3f}x OIDN")
        parts.append(f"{label} {validation[k]:.4g} ({', '.join(vs)})")
    if "blend_share" in validation:
        parts.append(
            f"blended {validation['blend_share']:.2f} : {1 - validation['blend_share']:.2f} with "
            f"{'fine-tuned ' if validation.get('blend_partner') else ''}OIDN, relMSE "
            f"{validation['blend_relmse']:.4g} ({validation['blend_relmse_vs_oidn']:.3f}x OIDN)"
        )
    return "; ".join(parts)


def _loop(run: _Run, readers: dict[str, PatchReader], val: dict[str, dict], start: int, resume: bool) -> None:
    """Steps start..settings.steps: every branch once per step, logging, validation and checkpoints."""
    settings = run.settings
    pin = run.device.type == "cuda"
    shard = (run.ranks.rank, run.ranks.world)
    streams = {
        b: iter(
            train_loader(
                readers[b],
                settings.batch_size,
                branch_seed(settings.seed, b),
                t.batches,
                settings.num_workers,
                pin,
                shard,
            )
        )
        for b, t in run.trainers.items()
    }
    if run.ranks.lead:
        run.metrics = MetricsLog(run.out_dir, resume_step=start if resume else None)
    else:
        val = {}  # rank 0 validates (the others wait for it in the next step's all-reduce)
    window = ProgressWindow(run, start)
    last_saved = start if resume else None
    try:
        if start == 0 and settings.val_every:
            _validate_all(run, val, 0)  # the starting weights: what the run must beat to ship anything else
        for step in range(start, start if run.clock.spent_before() else settings.steps):
            for b, trainer in run.trainers.items():
                batches = [next(streams[b]) for _ in range(trainer.batches_per_step(step))]
                ok, losses = trainer.step(step, batches)
                window.patches += len(batches) * settings.batch_size
                if ok:
                    window.averages.add(b, losses)
                    run.last_losses[b] = losses
                else:
                    _bad_step(run, b, trainer, step, last_saved)
            done = step + 1
            window.step_done(done)
            out_of_time = run.clock.budget > 0 and not agree(not run.clock.spent(), run.device)  # all ranks at one step
            last = done == settings.steps or out_of_time
            if settings.val_every and (done % settings.val_every == 0 or last):
                _validate_all(run, val, done)
            streak = any(t.bad_consecutive for t in run.trainers.values())
            if last or (done % settings.checkpoint_every == 0 and not streak):
                if run.ranks.lead:
                    save_checkpoint(run.checkpoint_path, run.state(done))
                last_saved = done
            run.step = done
            if out_of_time:
                run.say(
                    f"train.minutes = {settings.minutes:g}: the budget is spent, stopping at step {done} of "
                    f"{settings.steps} (raise train.minutes to train on)"
                )
                break
    except RankFailed as exc:
        kept = f"step {last_saved}" if last_saved is not None else "none written yet"
        raise RankFailed(f"{exc}; last checkpoint: {run.checkpoint_path} ({kept})") from None
    finally:
        window.close()
        if run.metrics is not None:
            run.metrics.close()
        del streams


def _bad_step(run: _Run, branch: str, trainer: BranchTrainer, step: int, last_saved: int | None) -> None:
    """Say a skipped step; stop with TrainingDiverged after max_bad_steps in a row."""
    run.say(
        f"step {step}: {branch} skipped, non-finite batch, loss or gradient "
        f"({trainer.bad_consecutive} in a row, {trainer.bad_total} in all)"
    )
    if trainer.bad_consecutive >= run.settings.max_bad_steps:
        kept = f"step {last_saved}" if last_saved is not None else "none written"
        raise TrainingDiverged(
            f"{branch}: {trainer.bad_consecutive} consecutive steps with non-finite batches, losses or "
            f"gradients (steps {step - trainer.bad_consecutive + 1}..{step}); stopped. Last good "
            f"checkpoint: {run.checkpoint_path} ({kept})"
        )


def _finish(run: _Run, start: int) -> TrainResult:
    """Write the shipped weights (each branch's best validated networks) and say which they are."""
    last_step = max(start, run.step)
    selected, selection_notes = run.best.summary(last_step, run.last_selection)
    run.notes.extend(selection_notes)  # said once, with the result, where the caller reports the weights file
    for note in selection_notes:
        log.info(note)
    trainers = run.trainers
    if run.ranks.lead:
        nets = {b: run.best.networks(b, t.shipped_generator, t.critic) for b, t in trainers.items()}
        blend = {b: run.blends[b][s["step"]] for b, s in selected.items() if s["step"] in run.blends.get(b, {})}
        partner = "OIDN fine-tuned here" if run.partner else "OIDN"
        for b, share in blend.items():
            run.notes.append(
                f"{b}: ships blended with {partner}, {share:.2f} of its own output (chosen on the val frames)"
            )
        if run.partner:
            run.notes.extend(_partner_notes(run.partner))
        export_weights(
            run.weights_path,
            nets,
            {
                "model": dataclasses.asdict(run.model),
                "transform": run.transform,
                "patch_size": run.patch_size,
                "stage": run.stage,
                "step": last_step,
                "selected": selected,
                "store_fingerprint": run.fingerprint,
                "precision": run.precision,
                **({OIDN_BLEND: blend} if blend else {}),
            },
            oidn_networks=run.partner.shipped() if run.partner else None,
        )
    return TrainResult(
        out_dir=run.out_dir,
        checkpoint=run.checkpoint_path,
        weights=run.weights_path,
        step=last_step,
        branches=list(trainers),
        skipped_branches=run.skipped,
        last_losses=run.last_losses,
        validation=run.validation,
        notes=run.notes,
        selected=selected,
        rank=run.ranks.rank,
    )


def _partner_notes(partner: Partner) -> list[str]:
    """What OIDN's fine-tune ships per branch: its step, what it learned from, and its val metrics against
    OIDN's own weights (or that those ship: no step beat them)."""
    notes = []
    for b in partner.shipped():
        if b not in partner.best_step:  # never validated (its step 0 validation sets it)
            continue
        step = partner.best_step[b]
        chosen = {"raw": " on the raw references", "cleaned": " on the cleaned targets"}.get(partner.chosen_targets(b))
        if step == 0:
            notes.append(
                f"{b}: OIDN's network ships its own weights: no step of its fine-tune ({partner.step} steps"
                f"{chosen or ''}) beat them on the val rows"
            )
            continue
        notes.append(
            f"{b}: OIDN's network ships step {step} of {partner.step} of its fine-tune{chosen or ''} "
            f"(val {_ratio_text(partner.ratios(b, partner.best_scores(b)))} OIDN's own weights)"
        )
    return notes


def _ratio_text(ratios: dict[str, float]) -> str:
    """{"relmse": 0.8, "hdr_flip": 0.9} -> "relMSE 0.800x, HDR-FLIP 0.900x"."""
    return ", ".join(f"{METRIC_LABELS[k]} {v:.3f}x" for k, v in ratios.items())
