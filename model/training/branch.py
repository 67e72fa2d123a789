"""One branch's (diffuse or specular) networks, optimisers and training step.

The authors' optimiser: Adam(0.9, 0.999, eps 1e-8) everywhere; the conditioned body and the
encoder learn at body_lr_factor x the branch's lr, head and tail at the lr and only from
head_tail_start_step on (two generator optimisers, as in their SFTGAN-based code); MultiStepLR on
each. An update whose loss or gradients are not finite is skipped (no optimiser or scheduler step),
so a bad batch never reaches the weights; the step counts as bad. The networks run in
train.precision (bf16 autocast or float32, channels_last either way: precision.py); the losses and the gradient
penalty are float32 whatever it is (losses.py). With train.ema > 0 the branch also keeps an exponential
moving average of the generator's weights, and that average is what validation scores and training
ships: it smooths the step-to-step noise that small batches leave in the weights. Under data-parallel
training (distributed.py) each rank steps on its shard of the batch: the gradients are averaged over the
ranks before the finite check and the optimiser step, and the ranks agree on skipping a step, so they
stay identical.
"""

from __future__ import annotations

import contextlib
import copy
import warnings
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from admc.stores.checkpoints import load_network

from ..nets.backbones import build_generator
from ..nets.critic import Critic
from ..nets.losses import critic_loss, generator_loss, log_floor
from ..nets.settings import ModelSettings
from ..precision import MEMORY_FORMAT, autocast_for, resolve_precision
from .data import IMAGE_KEYS
from .distributed import agree, average_gradients, average_values, current
from ..train_settings import TrainSettings
from .teacher import load_teacher
from .validation import linear_scale

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8


def _grads_finite(params: list[nn.Parameter]) -> bool:
    norms = [torch.linalg.vector_norm(p.grad.detach().float()) for p in params if p.grad is not None]
    return bool(torch.isfinite(torch.stack(norms)).all()) if norms else True


@contextlib.contextmanager
def _frozen(module: nn.Module) -> Iterator[None]:
    """No parameter gradients for `module` inside (the critic during a generator update)."""
    flags = [p.requires_grad for p in module.parameters()]
    for p in module.parameters():
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, flag in zip(module.parameters(), flags):
            p.requires_grad_(flag)


class BranchTrainer:
    """Generator + critic of one branch with their optimisers, schedulers and bad-step counters."""

    def __init__(
        self, branch: str, model: ModelSettings, settings: TrainSettings, patch_size: int, device: torch.device
    ):
        self.branch, self.settings, self.device = branch, settings, device
        ranks = current()
        self.shard = (ranks.rank, ranks.world)  # this process's slice of each global batch
        self.dtype = resolve_precision(settings.precision, device)
        self.generator = build_generator(model).to(device, memory_format=MEMORY_FORMAT)
        self.critic = Critic(model, patch_size).to(device, memory_format=MEMORY_FORMAT)
        self.patch_size = patch_size
        lr = settings.lr_g(branch)
        groups = self.generator.parameter_groups()
        self.optimizers = {
            "g_body": torch.optim.Adam(groups["body"], lr=lr * settings.body_lr_factor, betas=ADAM_BETAS, eps=ADAM_EPS),
            "g_head_tail": torch.optim.Adam(groups["head_tail"], lr=lr, betas=ADAM_BETAS, eps=ADAM_EPS),
            "critic": torch.optim.Adam(self.critic.parameters(), lr=settings.lr_d, betas=ADAM_BETAS, eps=ADAM_EPS),
        }
        self.schedulers = {
            name: torch.optim.lr_scheduler.MultiStepLR(opt, list(settings.lr_milestones), settings.lr_gamma)
            for name, opt in self.optimizers.items()
        }
        self.average = self._copy_of_generator() if settings.ema else None
        self.teacher = load_teacher(settings.distill_from, branch, model, device) if settings.distill_from else None
        self.average_updates = 0
        self.batches = 0  # batches consumed from the data stream (its resume position)
        self.bad_total = 0
        self.bad_consecutive = 0

    @property
    def shipped_generator(self) -> nn.Module:
        """The generator that validation scores and training ships: the moving average when train.ema > 0."""
        return self.average if self.average is not None else self.generator

    def _copy_of_generator(self) -> nn.Module:
        average = copy.deepcopy(self.generator).eval()
        for p in average.parameters():
            p.requires_grad_(False)
        return average

    @torch.no_grad()
    def _update_average(self) -> None:
        """average += (1 - decay) (weights - average), the decay ramped as min(ema, (1 + n) / (10 + n)) over the
        n updates so far, so a run from random weights does not carry them for thousands of steps."""
        decay = min(self.settings.ema, (1 + self.average_updates) / (10 + self.average_updates))
        self.average_updates += 1
        for averaged, weights in zip(self.average.parameters(), self.generator.parameters()):
            averaged.lerp_(weights, 1.0 - decay)
        for averaged, weights in zip(self.average.buffers(), self.generator.buffers()):
            averaged.copy_(weights)

    def batches_per_step(self, step: int) -> int:
        return self.settings.critic_steps_per_g if self.settings.phase(step) == "adversarial" else 1

    def _to_device(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        return {
            k: batch[k].to(self.device, non_blocking=True, memory_format=MEMORY_FORMAT)
            for k in IMAGE_KEYS
            if k in batch
        }

    def _critic_update(self, batch: dict[str, Tensor]) -> tuple[bool, dict[str, Tensor]]:
        with torch.no_grad(), autocast_for(self.device, self.dtype):
            fake = self.generator(batch["noisy"], batch["features"], batch.get("base"))
        opt = self.optimizers["critic"]
        opt.zero_grad(set_to_none=True)
        with autocast_for(self.device, self.dtype):
            loss, parts = critic_loss(self.critic, batch["reference"], fake, self.settings.gp_weight, self.shard)
        parts["critic_loss"] = loss.detach()
        if not agree(bool(torch.isfinite(loss)), self.device):
            return False, parts
        loss.backward()
        average_gradients(list(self.critic.parameters()))
        if not _grads_finite(list(self.critic.parameters())):
            opt.zero_grad(set_to_none=True)
            return False, parts
        opt.step()
        return True, parts

    def _generator_update(
        self, step: int, batch: dict[str, Tensor], adversarial: bool
    ) -> tuple[bool, dict[str, Tensor]]:
        for opt in (self.optimizers["g_body"], self.optimizers["g_head_tail"]):
            opt.zero_grad(set_to_none=True)
        s = self.settings
        with _frozen(self.critic), autocast_for(self.device, self.dtype):
            fake = self.generator(batch["noisy"], batch["features"], batch.get("base"))
            critic_fake = self.critic(fake) if adversarial else None
            loss, parts = generator_loss(
                fake,
                batch["reference"],
                critic_fake,
                s.l1_weight,
                s.adv_weight,
                adversarial,
                s.l1_floor,
                s.ssim_weight,
                linear_scale(batch["features"], self.branch) if s.ssim_weight else None,
            )
            if self.teacher is not None:
                with torch.no_grad():
                    taught = self.teacher(batch["noisy"], batch["features"], batch.get("base"))
                distill = F.l1_loss(log_floor(fake.float(), s.l1_floor), log_floor(taught.float(), s.l1_floor))
                parts["distill"] = distill.detach()
                loss = loss + s.distill_weight * distill
        parts["generator_loss"] = loss.detach()
        if not agree(bool(torch.isfinite(loss)), self.device):
            return False, parts
        loss.backward()
        average_gradients(list(self.generator.parameters()))
        if not _grads_finite(list(self.generator.parameters())):
            return False, parts
        self.optimizers["g_body"].step()
        if step >= s.head_tail_start_step:
            self.optimizers["g_head_tail"].step()
        if self.average is not None:
            self._update_average()
        return True, parts

    def step(self, step: int, batches: list[dict[str, Tensor]]) -> tuple[bool, dict[str, float]]:
        """One global step on `batches_per_step(step)` batches: critic update(s) then generator update
        as the phase asks. Returns (ok, losses); on a bad step no weights, optimiser states or
        schedulers changed."""
        phase = self.settings.phase(step)
        if len(batches) != self.batches_per_step(step):
            raise ValueError(
                f"{self.branch} step {step} ({phase}): needs {self.batches_per_step(step)} batches, got {len(batches)}"
            )
        self.batches += len(batches)
        batches = [self._to_device(b) for b in batches]
        self.generator.train()
        self.critic.train()
        # A non-finite input is refused before any forward pass: even a skipped update would
        # otherwise push it into BatchNorm running statistics (critic_norm = "batch").
        ok = agree(all(bool(torch.isfinite(t).all()) for b in batches for t in b.values()), self.device)
        parts: dict[str, Tensor] = {}
        if ok and phase in ("critic", "adversarial"):
            for batch in batches:
                good, p = self._critic_update(batch)
                ok, parts = ok and good, {**parts, **p}
        if ok and phase in ("l1", "adversarial"):
            good, p = self._generator_update(step, batches[-1], adversarial=phase == "adversarial")
            ok, parts = ok and good, {**parts, **p}
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        if ok:
            with warnings.catch_warnings():
                # Optimisers idle in this phase (critic during L1, head/tail early) still follow the
                # global step schedule; torch warns about a scheduler step without an optimiser step.
                warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step\\(\\)` before")
                for scheduler in self.schedulers.values():
                    scheduler.step()
            self.bad_consecutive = 0
        else:
            self.bad_total += 1
            self.bad_consecutive += 1
        return ok, {k: float(v) for k, v in average_values(parts, self.device).items()}

    def learning_rates(self) -> dict[str, float]:
        return {f"lr_{name}": opt.param_groups[0]["lr"] for name, opt in self.optimizers.items()}

    def state_dict(self) -> dict:
        average = (
            {}
            if self.average is None
            else {"average": self.average.state_dict(), "average_updates": self.average_updates}
        )
        return {
            "generator": self.generator.state_dict(),
            "critic": self.critic.state_dict(),
            **average,
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
            "batches": self.batches,
            "bad_total": self.bad_total,
            "bad_consecutive": self.bad_consecutive,
        }

    def load_state_dict(self, state: dict, source: str) -> None:
        self.load_networks(state["generator"], state["critic"], source)
        for k, opt in self.optimizers.items():
            opt.load_state_dict(state["optimizers"][k])
        for k, scheduler in self.schedulers.items():
            scheduler.load_state_dict(state["schedulers"][k])
        self.batches, self.bad_total = state["batches"], state["bad_total"]
        self.bad_consecutive = state["bad_consecutive"]
        if self.average is not None and "average" in state:
            load_network(
                self.average, state["average"], f"{source}: {self.branch} moving average", "the configured architecture"
            )
            self.average_updates = state["average_updates"]

    def load_networks(self, generator: dict[str, Tensor], critic: dict[str, Tensor], source: str) -> None:
        """Load weights (any float dtype), naming `source` and the mismatch if the architecture differs (the
        critic's classifier is sized for the patch, so a patch size change shows there)."""
        load_network(self.generator, generator, f"{source}: {self.branch} generator", "the configured architecture")
        load_network(
            self.critic,
            critic,
            f"{source}: {self.branch} critic",
            f"the configured architecture at tile.patch_size = {self.patch_size} (the critic's "
            "classifier is sized for the patch it was trained on)",
        )
        if self.average is not None:  # the average starts from the loaded weights (a checkpoint's own follows)
            self.average.load_state_dict(self.generator.state_dict())
            self.average_updates = 0
