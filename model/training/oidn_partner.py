"""OIDN's own networks fine-tuned on the domain (train.oidn_minutes): the partner a fine-tuned admc blends with.

OIDN cannot be retrained through its library, but its networks can be: model/nets/oidn_unet.py runs them in
torch from the very weights the library runs. Before admc's own fine-tune, each branch's OIDN network (diffuse
with albedo and normal, specular alone: how admc runs OIDN) trains for train.oidn_minutes on the store's train
rows with train.oidn_loss in OIDN's PU domain (where it was trained), and keeps the validated step with the
lowest val error: the geometric mean of its mean val relMSE's and HDR-FLIP's ratios to the library's weights
(train.oidn_select; relMSE alone with "relmse"), which stay unless a later step beats them. On a store that
keeps its raw references beside cleaned targets (tile.clean_targets), each branch first tries both targets
(Partner). admc's blend share (train.oidn_blend) is then chosen against this partner, and the weights file
ships it. On three domains of scripts/make_domain_scenes.py this took OIDN's error to 0.84-0.98x at 4 spp and
about 0.9x at 16 and 64 spp (docs/results/2026-12-06-fine-tuned-oidn.md).

With train.oidn_network = "large" the diffuse branch starts from OIDN's final-frame route instead: its large
network for clean guides, on albedo and normal OIDN's own guide networks denoise first (PrefilteredGuides; the val
rows once), at its own rate (train.oidn_lr_large: at oidn_lr it lost HDR-FLIP within 100 steps). On two interiors
its blend scored below the standard partner's in every cell of Table 1:
docs/results/2026-12-08-oidn-final-frame-route.md.

The networks train and validate in float32 whatever train.precision says: the OIDN library runs them in
float32, and trained in bf16 autocast (2.4x the steps in the same minutes on an AMX Xeon) they ended with 3-5%
more HDR-FLIP on a product domain's test frames. They are channels_last like admc's (1.35x the steps of NCHW
on 2 cores). The phase is resumable: its state rides in the run's checkpoint (step 0 of admc's own steps).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from admc.common.layout import ALBEDO, NORMAL, RAW, branch_of
from admc.common.metrics import hdr_flip, relmse_torch
from admc.errors import TrainingError
from admc.stores.patches import PatchReader

from ..nets.losses import oidn_loss
from ..nets.oidn_unet import (
    INPUT_CHANNELS,
    OidnUNet,
    batch_exposure,
    clean_guides,
    network_for,
    network_input,
    oidn_unet,
    transfer,
    uses_clean_guides,
)
from ..precision import MEMORY_FORMAT
from ..train_settings import OIDN_SELECTIONS, TrainSettings
from .clock import Clock
from .data import branch_seed, spread_rows, train_loader
from .validation import to_linear

PARTNER_SEED_OFFSET = 7919
"""The partner's batch stream differs from admc's branch streams (same store, same seed)."""


CANDIDATES = {"diffuse": (RAW,), "specular": ("", RAW)}
"""What each branch's network learns from where the store keeps raw references beside cleaned targets
(tile.clean_targets): the diffuse one the raw references, cleaned where they have not converged
(tile.partner_references; its best val step beat the cleaned targets' on all four domains measured, by 1-9%,
against 256-spp val references, which favour darker outputs: docs/results/2026-12-07-val-references.md),
the specular one both, until the first validation after step 0, then the
better alone (which one pays flips by domain: docs/results/2026-12-06-fine-tuned-oidn.md)."""

Scores = dict[str, float]
"""A validation's mean val metrics: "relmse", and "hdr_flip" where the selection uses it."""


@dataclass
class Partner:
    """Each branch's OIDN network in training, its best validated state and where the phase stands.

    A branch's networks in training are its candidates (CANDIDATES): one, or two on trial until the first
    validation after step 0, which keeps the better.
    """

    nets: dict[str, OidnUNet]  # candidate -> network
    optimizers: dict[str, torch.optim.Optimizer]  # candidate -> its Adam
    select: str  # train.oidn_select: which metrics rank the steps (OIDN_SELECTIONS)
    best: dict[str, dict[str, Tensor]] = field(default_factory=dict)  # branch -> state dict of the best step
    best_step: dict[str, int] = field(default_factory=dict)
    scores: dict[str, dict[int, Scores]] = field(default_factory=dict)  # candidate -> step -> its val metrics
    step: int = 0
    seconds: float = 0.0
    done: bool = False
    val_outputs: dict[str, Tensor] = field(default_factory=dict)  # branch -> the best nets' linear val output

    @property
    def on_trial(self) -> list[str]:
        """The branches whose two targets are both still training."""
        return [branch_of(name) for name in self.nets if name.endswith(RAW) and branch_of(name) in self.nets]

    def candidates(self, branch: str) -> list[str]:
        return [name for name in self.nets if branch_of(name) == branch]

    def state_dict(self) -> dict:
        return {
            "nets": {name: net.state_dict() for name, net in self.nets.items()},
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
            "best": self.best,
            "best_step": self.best_step,
            "scores": self.scores,
            "step": self.step,
            "seconds": self.seconds,
            "done": self.done,
        }

    def load_state_dict(self, state: dict) -> None:
        scores = [s for candidate in state.get("scores", {}).values() for s in candidate.values()]
        if "optimizers" not in state or not all(isinstance(s, dict) for s in scores):
            raise TrainingError(
                "the checkpoint's OIDN fine-tune was written by an older admc, whose state this one cannot resume; "
                "start the run afresh (without --resume, in a new run.workdir or after removing the old run)"
            )
        for name in list(self.nets):  # a branch whose targets were chosen has one candidate left
            if name not in state["nets"]:
                del self.nets[name], self.optimizers[name]
        for name, net in self.nets.items():
            net.load_state_dict(state["nets"][name])
            self.optimizers[name].load_state_dict(state["optimizers"][name])
        self.best, self.best_step, self.scores = state["best"], state["best_step"], state["scores"]
        self.step, self.seconds, self.done = int(state["step"]), float(state["seconds"]), bool(state["done"])

    def shipped(self) -> dict[str, dict[str, Tensor]]:
        """branch -> the state dict the weights file ships (the best validated step's)."""
        return {
            b: self.best.get(b, self.nets[self.candidates(b)[0]].state_dict())
            for b in dict.fromkeys(branch_of(name) for name in self.nets)
        }

    def start_scores(self, branch: str) -> Scores:
        """The branch's val metrics at step 0: OIDN's own weights (or the ones the run started from)."""
        return next(scores[0] for name, scores in self.scores.items() if branch_of(name) == branch and 0 in scores)

    def ratios(self, branch: str, scores: Scores) -> Scores:
        """Each of `scores`' metrics over the branch's at step 0 (1 where step 0's is 0)."""
        start = self.start_scores(branch)
        return {k: v / start[k] if start[k] else 1.0 for k, v in scores.items()}

    def error(self, branch: str, scores: Scores) -> float:
        """What ranks the branch's validated steps: the geometric mean of the selected metrics' ratios to
        step 0 (1 at step 0)."""
        ratios = self.ratios(branch, scores)
        selected = OIDN_SELECTIONS[self.select]
        return math.prod(ratios[k] for k in selected) ** (1 / len(selected))

    def best_scores(self, branch: str) -> Scores:
        """The val metrics of the branch's lowest-error validation, a dropped candidate's included."""
        every = [s for name, scores in self.scores.items() if branch_of(name) == branch for s in scores.values()]
        return min(every, key=lambda s: self.error(branch, s))

    def chosen_targets(self, branch: str) -> str | None:
        """What the branch's network learns from on a store with both targets ("raw" or "cleaned"); None on a
        store without, or while its trial runs."""
        if branch + RAW not in self.scores or branch in self.on_trial:
            return None
        return "raw" if self.candidates(branch) == [branch + RAW] else "cleaned"


def start_partner(
    branches: list[str],
    settings: TrainSettings,
    init: dict[str, dict] | None,
    device: torch.device,
    raw_references: list[str] = (),
) -> Partner:
    """The branches' OIDN networks from `init` (a fine-tuned partner a weights file ships, of its own size) or
    the library's (train.oidn_network); the branches in `raw_references` (their store keeps them beside cleaned
    targets) get their CANDIDATES."""
    nets = {}
    for name in [b + suffix for b in branches for suffix in (CANDIDATES[b] if b in raw_references else ("",))]:
        b = branch_of(name)
        if init and b in init:
            net = network_for(init[b], INPUT_CHANNELS[b])
            net.load_state_dict({k: v.float() for k, v in init[b].items()})
        else:
            net = oidn_unet(b, settings.oidn_network)
        nets[name] = net.to(device, memory_format=MEMORY_FORMAT).train()
    optimizers = {
        name: torch.optim.Adam(
            net.parameters(), lr=settings.oidn_lr_large if uses_clean_guides(net) else settings.oidn_lr
        )
        for name, net in nets.items()
    }
    return Partner(nets, optimizers, settings.oidn_select)


def finetune_partner(
    partner: Partner,
    settings: TrainSettings,
    readers: dict[str, PatchReader],
    val: dict[str, dict[str, Tensor]],
    device: torch.device,
    save: Callable[[], None],
    show: Callable[[str], None],
    progress: bool = False,
) -> None:
    """Train `partner` until train.oidn_minutes of its own time are spent (across resumes), validating every
    train.val_every steps and at the end; `save` is called after each validation (a checkpoint). Fills
    partner.val_outputs with the shipped networks' output on the val rows."""
    clock = Clock(settings.oidn_minutes, before=partner.seconds)
    if not partner.done:
        streams = {
            b: iter(
                train_loader(
                    _rows_for(partner, b, r),
                    settings.batch_size,
                    branch_seed(settings.seed, b) + PARTNER_SEED_OFFSET,
                    partner.step,
                    settings.num_workers,
                )
            )
            for b, r in readers.items()
        }
        if partner.step == 0:
            _validate(partner, val, settings.batch_size, device, show)
        bar = tqdm(
            total=round(clock.budget),
            initial=round(clock.before),
            unit="s",
            desc="OIDN fine-tune",
            disable=not progress,
        )
        while True:
            for b in readers:
                batch = next(streams[b])  # one batch for both of a branch's candidates: a fair trial
                for name in partner.candidates(b):
                    x, target = _pairs(batch, b, "raw_reference" if name.endswith(RAW) else "reference", device)
                    loss = oidn_loss(partner.nets[name](x), target, settings.oidn_loss)
                    partner.optimizers[name].zero_grad(set_to_none=True)
                    loss.backward()
                    partner.optimizers[name].step()
            partner.step += 1
            partner.seconds = clock.seconds()
            bar.update(min(round(partner.seconds), round(clock.budget)) - bar.n)
            bar.set_postfix(step=partner.step, loss=f"{loss.item():.4g}", refresh=False)
            spent = clock.spent()
            if spent or (settings.val_every and partner.step % settings.val_every == 0):
                _validate(partner, val, settings.batch_size, device, show)
                _choose_targets(partner, show)
                partner.done = spent
                save()
            if spent:
                break
        bar.close()
        del streams
    for b, state in partner.shipped().items():
        if b in val:
            shipped = network_for(state, INPUT_CHANNELS[b]).to(device, memory_format=MEMORY_FORMAT)
            shipped.load_state_dict(state)
            partner.val_outputs[b] = _run(shipped, val[b], b, settings.batch_size, device)


def _choose_targets(partner: Partner, show: Callable[[str], None]) -> None:
    """At the first validation after step 0, each branch on trial keeps the candidate with the lower val
    error (the store's targets on a tie) and drops the other with its optimizer."""
    for b in partner.on_trial:
        twin = b + RAW
        mine, raw = partner.scores.get(b, {}).get(partner.step), partner.scores.get(twin, {}).get(partner.step)
        if raw is not None and mine is not None:
            mine, raw = partner.error(b, mine), partner.error(b, raw)
        loser = twin if raw is None or mine is None or mine <= raw else b
        del partner.nets[loser], partner.optimizers[loser]
        if raw is not None and mine is not None:
            kept = "raw" if loser == b else "cleaned"
            show(
                f"OIDN fine-tune {b}: goes on with the {kept} targets (val error at step {partner.step}: "
                f"cleaned {mine:.4g}x OIDN's, raw {raw:.4g}x)"
            )


def _rows_for(partner: Partner, branch: str, reader: PatchReader):
    """What the branch's networks train on: the reader's rows, with their raw references where a candidate
    learns them, and with prefiltered guides for a large network."""
    if any(name.endswith(RAW) for name in partner.candidates(branch)):
        reader = reader.with_raw_references()
    if any(uses_clean_guides(partner.nets[name]) for name in partner.candidates(branch)):
        return PrefilteredGuides(reader)
    return reader


class PrefilteredGuides:
    """A reader's rows with the albedo and normal in their features denoised by OIDN's own guide networks (the
    large network's input: nets/oidn_unet.py), each row once (0.1-0.2 s a patch on 2 cores, cached: a float32
    copy of the two guides, 0.4 MB a 128x128 row). The batch's symmetry then applies to the prefiltered guides,
    where inference prefilters the image it sees; OIDN's networks are trained for every orientation."""

    def __init__(self, reader: PatchReader) -> None:
        self.reader = reader
        self.guides: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, i: int) -> dict:
        item = self.reader[i]
        features = item["features"].copy()
        if i not in self.guides:
            albedo, normal = clean_guides(*_guides(torch.from_numpy(features)[None], "diffuse"))
            self.guides[i] = albedo[0].numpy(), normal[0].numpy() * 0.5 + 0.5
        features[ALBEDO], features[NORMAL] = self.guides[i]
        return {**item, "features": features}


def _pairs(batch: dict[str, Tensor], branch: str, target: str, device: torch.device) -> tuple[Tensor, Tensor]:
    """(network input, target in the network's domain) of a store batch of one branch (its guides prefiltered
    already where the network takes them so: PrefilteredGuides); `target`: the batch's entry to learn
    ("reference", or "raw_reference" for a candidate on the raw references)."""
    features = batch["features"].to(device)
    noisy = to_linear(batch["noisy"].to(device), features, branch).float()
    reference = to_linear(batch[target].to(device), features, branch).float()
    exposure = batch_exposure(noisy)
    x = network_input(noisy, exposure, *_guides(features, branch)).contiguous(memory_format=MEMORY_FORMAT)
    return x, transfer(reference * exposure)


def _guides(features: Tensor, branch: str) -> tuple[Tensor, ...]:
    """The diffuse network's albedo and normal (in [-1, 1]) from a batch's features; none for the specular one."""
    return (features[:, ALBEDO], features[:, NORMAL] * 2 - 1) if branch == "diffuse" else ()


@torch.no_grad()
def _run(net: OidnUNet, rows: dict[str, Tensor], branch: str, batch_size: int, device: torch.device) -> Tensor:
    """The network's linear output on the val rows (float64, as validation.to_linear gives)."""
    was_training = net.training
    net.eval()
    outputs = []
    clean = uses_clean_guides(net)
    for i in range(0, len(rows["noisy"]), batch_size):
        features = rows["features"][i : i + batch_size].to(device)
        noisy = to_linear(rows["noisy"][i : i + batch_size].to(device), features, branch).float()
        guides = _val_guides(rows, branch, i, batch_size, device) if clean else _guides(features, branch)
        outputs.append(net.denoise(noisy, batch_exposure(noisy), *guides).double().cpu())
    net.train(was_training)
    return torch.cat(outputs)


def _val_guides(rows: dict[str, Tensor], branch: str, start: int, count: int, device) -> tuple[Tensor, ...]:
    """Prefiltered guides of val rows start..start+count, prefiltered once (OIDN's guide networks take about a
    tenth of a second a patch) and kept with the rows."""
    if "clean_guides" not in rows:
        rows["clean_guides"] = clean_guides(*_guides(rows["features"].float(), branch))
    return tuple(g[start : start + count].to(device) for g in rows["clean_guides"])


def _validate(partner: Partner, val: dict, batch_size: int, device: torch.device, show: Callable[[str], None]) -> None:
    """Score every candidate on its branch's val rows; keep it if it is the branch's best so far. At step 0 a
    branch's two candidates are one (the start weights) and share a score."""
    for name, net in partner.nets.items():
        b = branch_of(name)
        if b not in val:
            continue
        scores = partner.scores.setdefault(name, {})
        if partner.step == 0 and name.endswith(RAW) and b in partner.nets:
            scores[0] = partner.scores[b][0]
            continue
        rows = val[b]
        reference = to_linear(rows["reference"], rows["features"], b)
        output = _run(net, rows, b, batch_size, device)
        score = {"relmse": float(relmse_torch(output, reference).mean())}
        if "hdr_flip" in OIDN_SELECTIONS[partner.select]:
            score["hdr_flip"] = _mean_flip(output, reference)
        scores[partner.step] = score
        if partner.error(b, score) <= partner.error(b, partner.best_scores(b)):
            partner.best[b] = {k: v.detach().clone().cpu() for k, v in net.state_dict().items()}
            partner.best_step[b] = partner.step
        label = f"{b}, raw targets" if name.endswith(RAW) else b
        ratios = partner.ratios(b, score)
        metrics = ", ".join(f"{METRIC_LABELS[k]} {v:.4g} ({ratios[k]:.3f}x OIDN's)" for k, v in score.items())
        show(f"OIDN fine-tune step {partner.step} {label}: val {metrics}; best step {partner.best_step[b]}")


METRIC_LABELS = {"relmse": "relMSE", "hdr_flip": "HDR-FLIP"}

FLIP_ROWS = 64
"""HDR-FLIP scores at most this many val rows, spread over them: 0.03 CPU-seconds a 128x128 patch (1.4-2.0 s for
the 48-60 val rows of two domains), so on a large val split it stays near 2 s a validation per branch."""


def _mean_flip(output: Tensor, reference: Tensor) -> float:
    """The mean HDR-FLIP of (N, 3, H, W) linear patches (FLIP_ROWS of those whose reference has light; 0 if
    none has): what a viewer sees, which relMSE under-weights (on one domain OIDN's longer fine-tune lowered
    the val relMSE and raised the HDR-FLIP). A black reference is left to relMSE: HDR-FLIP would take its
    exposure from the output, so a haze of 1e-9 scores near 1. On an interior whose specular val rows were
    31% black, that hid a fine-tune better on every lit row and kept step 100 of 637."""
    lit = torch.nonzero(reference.flatten(1).amax(1) > 0).flatten().tolist()
    if not lit:
        return 0.0
    rows = [lit[k] for k in spread_rows(len(lit), FLIP_ROWS)]
    pairs = zip(output[rows].float().numpy(), reference[rows].float().numpy())
    return float(np.mean([hdr_flip(x.transpose(1, 2, 0), ref.transpose(1, 2, 0)) for x, ref in pairs]))
