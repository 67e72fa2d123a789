"""Which networks a training run ships: each branch's best by validation, not its last.

Each branch is validated on the same fixed val patches before its first step (the starting weights: the
ones fine-tuning starts from, or an untrained network) and every val_every steps after; it keeps a CPU
copy of its networks whenever its validation value is the lowest so far. A run that peaks early ships
the peak. The value (train.select_metric) is the mean relMSE, or "relmse+ssim": per patch, the mean of
its relMSE and its 1-SSIM, each divided by the noisy input's mean over the val patches. relMSE alone is
blind to an error of a few 8-bit levels in a deep shadow, which 1-SSIM counts among the largest.

A run that starts from given weights (fine-tuning) must not ship something worse than them, and a mean
over a few dozen val patches moves by a percent or more between two near-identical networks. So a step
replaces the starting weights only if it beats them by `min_z` standard errors of the paired per-patch
differences (one-sided z test); otherwise the weights file keeps the starting weights and says so. The
patches of one scene are not independent, so the test is, if anything, too lenient: it guards against
noise, and a small val split remains a small val split. (A run resumed with other train.val_patches has
other val patches than its starting weights were scored on; it then compares means only.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..train_settings import SELECT_METRIC_LABELS


def selection_values(metric: str, per_patch: dict[str, Tensor], scores: dict[str, float]) -> Tensor:
    """The per-patch values that rank validated steps under `metric` (one of settings.SELECT_METRICS)."""
    if metric == "relmse":
        return per_patch["relmse"]
    shares = [per_patch[k] / max(scores[f"noisy_{k}"], 1e-12) for k in ("relmse", "one_minus_ssim")]
    return (shares[0] + shares[1]) / 2


def selected_key(metric: str) -> str:
    """The key of a selected step's value in a weights file's metadata: val_relmse, val_relmse_ssim."""
    return "val_" + metric.replace("+", "_")


@dataclass
class Best:
    step: int
    value: float
    networks: dict[str, dict[str, torch.Tensor]]  # {"generator": state_dict, "critic": state_dict} on the CPU


@dataclass
class Unproven:
    """The lowest-valued step that did not beat the starting weights by enough: reported, not shipped."""

    step: int
    value: float
    z: float


def _cpu_copy(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu", copy=True) for k, v in module.state_dict().items()}


def improvement_z(start: Tensor, candidate: Tensor) -> float:
    """How many standard errors the mean per-patch value of `candidate` lies below that of `start`
    (paired, same patches); +inf when every patch improves by the same amount, nan with one patch."""
    diff = (start.double() - candidate.double()).flatten()
    if diff.numel() < 2:
        return math.nan
    mean, spread = float(diff.mean()), float(diff.std())
    if spread == 0:
        return math.inf if mean > 0 else (0.0 if mean == 0 else -math.inf)
    return mean / (spread / math.sqrt(diff.numel()))


class BestNetworks:
    """Per branch, the networks at the lowest validation value seen so far (ties keep the earlier step);
    with guarded starting weights, only among the steps that beat those by `min_z` standard errors."""

    def __init__(self, min_z: float = 2.0, metric: str = "relmse") -> None:
        self.min_z, self.metric = min_z, metric
        self.best: dict[str, Best] = {}
        self.start: dict[str, Tensor] = {}  # per-patch values of the guarded starting weights
        self.unproven: dict[str, Unproven] = {}

    def offer(
        self,
        branch: str,
        step: int,
        per_patch: Tensor,
        generator: torch.nn.Module,
        critic: torch.nn.Module,
        guard: bool = False,
    ) -> bool:
        """Keep these networks if their mean per-patch value beats the branch's best (and, once starting
        weights are guarded, beats those significantly); True when it did. `guard` marks the starting
        weights of a fine-tuning: they are kept, and later steps must prove themselves against them."""
        per_patch = per_patch.detach().to("cpu", torch.float64).flatten()
        value = float(per_patch.mean())
        current = self.best.get(branch)
        if current is not None and not value < current.value:
            return False
        start = self.start.get(branch)
        if start is not None and start.shape == per_patch.shape:
            z = improvement_z(start, per_patch)
            if not z >= self.min_z:
                seen = self.unproven.get(branch)
                if seen is None or value < seen.value:
                    self.unproven[branch] = Unproven(step, value, z)
                return False
        if guard:
            self.start[branch] = per_patch
        self.best[branch] = Best(step, value, {"generator": _cpu_copy(generator), "critic": _cpu_copy(critic)})
        return True

    def networks(self, branch: str, generator: torch.nn.Module, critic: torch.nn.Module) -> dict:
        """The branch's best networks, or the given (last) ones where it was never validated."""
        best = self.best.get(branch)
        if best is None:
            return {"generator": generator.state_dict(), "critic": critic.state_dict()}
        return best.networks

    def summary(self, last_step: int, last: dict[str, float]) -> tuple[dict[str, dict], list[str]]:
        """({branch: {"step", selected_key}}, sentences for the user) for the weights this run ships."""
        selected, notes, label = {}, [], SELECT_METRIC_LABELS[self.metric]
        for branch, best in self.best.items():
            selected[branch] = {"step": best.step, selected_key(self.metric): best.value}
            unproven = self.unproven.get(branch)
            if best.step == 0 and unproven is not None and unproven.value < best.value:
                gain = 100 * (1 - unproven.value / best.value)
                notes.append(
                    f"{branch}: step {unproven.step} was {gain:.2g}% below the starting weights on validation "
                    f"({label} {unproven.value:.5g} against {best.value:.5g}), within the noise of the val "
                    f"patches ({unproven.z:.2g} standard errors; train.select_z asks {self.min_z:g}); the "
                    f"weights file keeps the starting weights unchanged"
                )
            elif best.step == 0 and last_step > 0:
                notes.append(
                    f"{branch}: no step beat the starting weights on validation ({label} {best.value:.5g} "
                    f"at step 0); the weights file keeps them unchanged"
                )
            elif best.step != last_step and branch in last:
                notes.append(
                    f"{branch}: the weights file holds step {best.step} (validation {label} "
                    f"{best.value:.5g}), better than the last step {last_step} ({last[branch]:.5g})"
                )
        return selected, notes

    def state_dict(self) -> dict:
        return {
            b: {
                "step": x.step,
                "value": x.value,
                "networks": x.networks,
                "start": self.start.get(b),
                "unproven": vars(self.unproven[b]) if b in self.unproven else None,
            }
            for b, x in self.best.items()
        }

    def load_state_dict(self, state: dict) -> None:
        self.best = {b: Best(x["step"], x["value"], x["networks"]) for b, x in state.items()}
        self.start = {b: x["start"] for b, x in state.items() if x.get("start") is not None}
        self.unproven = {b: Unproven(**x["unproven"]) for b, x in state.items() if x.get("unproven") is not None}
