"""Which networks a training run ships: each branch's best by validation, not its last.

Each branch is validated on the same fixed val patches before its first step (the starting weights: the
ones fine-tuning starts from, or an untrained network) and every val_every steps after; it keeps a CPU
copy of its networks whenever its validation relMSE is the lowest so far. A fine-tuning that never beats
its starting weights therefore ships them unchanged and says so, and a run that peaks early ships the peak.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

SELECTION_METRIC = "relmse"


@dataclass
class Best:
    step: int
    value: float
    networks: dict[str, dict[str, torch.Tensor]]  # {"generator": state_dict, "critic": state_dict} on the CPU


def _cpu_copy(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu", copy=True) for k, v in module.state_dict().items()}


class BestNetworks:
    """Per branch, the networks at the lowest validation relMSE seen so far (ties keep the earlier step)."""

    def __init__(self) -> None:
        self.best: dict[str, Best] = {}

    def offer(self, branch: str, step: int, value: float, generator: torch.nn.Module,
              critic: torch.nn.Module) -> bool:
        """Keep these networks if `value` beats the branch's best; True when it did."""
        current = self.best.get(branch)
        if current is not None and not value < current.value:
            return False
        self.best[branch] = Best(step, value, {"generator": _cpu_copy(generator), "critic": _cpu_copy(critic)})
        return True

    def networks(self, branch: str, generator: torch.nn.Module, critic: torch.nn.Module) -> dict:
        """The branch's best networks, or the given (last) ones where it was never validated."""
        best = self.best.get(branch)
        if best is None:
            return {"generator": generator.state_dict(), "critic": critic.state_dict()}
        return best.networks

    def summary(self, last_step: int, last: dict[str, float]) -> tuple[dict[str, dict], list[str]]:
        """({branch: {"step", "val_relmse"}}, sentences for the user) for the weights this run ships."""
        selected, notes = {}, []
        for branch, best in self.best.items():
            selected[branch] = {"step": best.step, f"val_{SELECTION_METRIC}": best.value}
            if best.step == 0 and last_step > 0:
                notes.append(f"{branch}: no step beat the starting weights on validation (relMSE {best.value:.5g} "
                             f"at step 0); the weights file keeps them unchanged")
            elif best.step != last_step and branch in last:
                notes.append(f"{branch}: the weights file holds step {best.step} (validation relMSE "
                             f"{best.value:.5g}), better than the last step {last_step} ({last[branch]:.5g})")
        return selected, notes

    def state_dict(self) -> dict:
        return {b: {"step": x.step, "value": x.value, "networks": x.networks} for b, x in self.best.items()}

    def load_state_dict(self, state: dict) -> None:
        self.best = {b: Best(x["step"], x["value"], x["networks"]) for b, x in state.items()}
