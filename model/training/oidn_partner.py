"""OIDN's own networks fine-tuned on the domain (train.oidn_minutes): the partner a fine-tuned admc blends with.

OIDN cannot be retrained through its library, but its networks can be: model/nets/oidn_unet.py runs them in
torch from the very weights the library runs. Before admc's own fine-tune, each branch's OIDN network (diffuse
with albedo and normal, specular alone: how admc runs OIDN) trains for train.oidn_minutes on the store's train
rows, L1 in OIDN's PU domain (where it was trained), and keeps the validated step with the lowest mean val
relMSE: the library's weights unless a later step beats them. admc's blend share (train.oidn_blend) is then
chosen against this partner, and the weights file ships it. On three domains of scripts/make_domain_scenes.py
this took OIDN's error to 0.84-0.98x at 4 spp and about 0.9x at 16 and 64 spp
(docs/results/2026-12-06-fine-tuned-oidn.md).

The phase is resumable: its state rides in the run's checkpoint (step 0 of admc's own steps).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor
from tqdm import tqdm

from admc.common.layout import ALBEDO, NORMAL
from admc.common.metrics import relmse_torch
from admc.stores.patches import PatchReader

from ..nets.oidn_unet import OidnUNet, batch_exposure, network_input, oidn_unet, transfer
from ..train_settings import TrainSettings
from .clock import Clock
from .data import branch_seed, train_loader
from .validation import to_linear

PARTNER_SEED_OFFSET = 7919
"""The partner's batch stream differs from admc's branch streams (same store, same seed)."""


@dataclass
class Partner:
    """Each branch's OIDN network in training, its best validated state and where the phase stands."""

    nets: dict[str, OidnUNet]
    optimizer: torch.optim.Optimizer
    best: dict[str, dict[str, Tensor]] = field(default_factory=dict)  # branch -> state dict of the best step
    best_step: dict[str, int] = field(default_factory=dict)
    scores: dict[str, dict[int, float]] = field(default_factory=dict)  # branch -> step -> mean val relMSE
    step: int = 0
    seconds: float = 0.0
    done: bool = False
    val_outputs: dict[str, Tensor] = field(default_factory=dict)  # branch -> the best nets' linear val output

    def state_dict(self) -> dict:
        return {
            "nets": {b: net.state_dict() for b, net in self.nets.items()},
            "optimizer": self.optimizer.state_dict(),
            "best": self.best,
            "best_step": self.best_step,
            "scores": self.scores,
            "step": self.step,
            "seconds": self.seconds,
            "done": self.done,
        }

    def load_state_dict(self, state: dict) -> None:
        for b, net in self.nets.items():
            net.load_state_dict(state["nets"][b])
        self.optimizer.load_state_dict(state["optimizer"])
        self.best, self.best_step, self.scores = state["best"], state["best_step"], state["scores"]
        self.step, self.seconds, self.done = int(state["step"]), float(state["seconds"]), bool(state["done"])

    def shipped(self) -> dict[str, dict[str, Tensor]]:
        """branch -> the state dict the weights file ships (the best validated step's)."""
        return {b: self.best.get(b, net.state_dict()) for b, net in self.nets.items()}


def start_partner(
    branches: list[str], settings: TrainSettings, init: dict[str, dict] | None, device: torch.device
) -> Partner:
    """The branches' OIDN networks from `init` (a fine-tuned partner a weights file ships) or the library's."""
    nets = {}
    for b in branches:
        net = oidn_unet(b)
        if init and b in init:
            net.load_state_dict({k: v.float() for k, v in init[b].items()})
        nets[b] = net.to(device).train()
    params = [p for net in nets.values() for p in net.parameters()]
    return Partner(nets, torch.optim.Adam(params, lr=settings.oidn_lr))


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
                    r,
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
            for b, net in partner.nets.items():
                x, target = _pairs(next(streams[b]), b, device)
                loss = (net(x) - target).abs().mean()
                partner.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                partner.optimizer.step()
            partner.step += 1
            partner.seconds = clock.seconds()
            bar.update(min(round(partner.seconds), round(clock.budget)) - bar.n)
            bar.set_postfix(step=partner.step, loss=f"{loss.item():.4g}", refresh=False)
            spent = clock.spent()
            if spent or (settings.val_every and partner.step % settings.val_every == 0):
                _validate(partner, val, settings.batch_size, device, show)
                partner.done = spent
                save()
            if spent:
                break
        bar.close()
        del streams
    for b, net in partner.nets.items():
        if b in val:
            shipped = OidnUNet(net.enc_conv0.in_channels).to(device)
            shipped.load_state_dict(partner.shipped()[b])
            partner.val_outputs[b] = _run(shipped, val[b], b, settings.batch_size, device)


def _pairs(batch: dict[str, Tensor], branch: str, device: torch.device) -> tuple[Tensor, Tensor]:
    """(network input, target in the network's domain) of a store batch of one branch."""
    features = batch["features"].to(device)
    noisy = to_linear(batch["noisy"].to(device), features, branch).float()
    reference = to_linear(batch["reference"].to(device), features, branch).float()
    exposure = batch_exposure(noisy)
    return network_input(noisy, exposure, *_guides(features, branch)), transfer(reference * exposure)


def _guides(features: Tensor, branch: str) -> tuple[Tensor, ...]:
    """The diffuse network's albedo and normal (in [-1, 1]) from a batch's features; none for the specular one."""
    return (features[:, ALBEDO], features[:, NORMAL] * 2 - 1) if branch == "diffuse" else ()


@torch.no_grad()
def _run(net: OidnUNet, rows: dict[str, Tensor], branch: str, batch_size: int, device: torch.device) -> Tensor:
    """The network's linear output on the val rows (float64, as validation.to_linear gives)."""
    was_training = net.training
    net.eval()
    outputs = []
    for i in range(0, len(rows["noisy"]), batch_size):
        features = rows["features"][i : i + batch_size].to(device)
        noisy = to_linear(rows["noisy"][i : i + batch_size].to(device), features, branch).float()
        outputs.append(net.denoise(noisy, batch_exposure(noisy), *_guides(features, branch)).double().cpu())
    net.train(was_training)
    return torch.cat(outputs)


def _validate(partner: Partner, val: dict, batch_size: int, device: torch.device, show: Callable[[str], None]) -> None:
    """Score every branch's network on its val rows; keep it if it is the best so far."""
    for b, net in partner.nets.items():
        if b not in val:
            continue
        rows = val[b]
        reference = to_linear(rows["reference"], rows["features"], b)
        score = float(relmse_torch(_run(net, rows, b, batch_size, device), reference).mean())
        scores = partner.scores.setdefault(b, {})
        scores[partner.step] = score
        if score <= min(scores.values()):
            partner.best[b] = {k: v.detach().clone().cpu() for k, v in net.state_dict().items()}
            partner.best_step[b] = partner.step
        line = f"OIDN fine-tune step {partner.step} {b}: val relMSE {score:.4g} ({score / scores[0]:.3f}x OIDN's"
        show(line + f"; best step {partner.best_step[b]})")
