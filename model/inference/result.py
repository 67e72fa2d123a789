"""What a FullImageDenoiser returns: the denoised image, its parts, what was repaired and what it cost."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class DenoiseResult:
    """One denoised image, its parts, what was repaired on the way in, and what it cost."""

    image: np.ndarray  # (H, W, 3) float32 linear HDR: diffuse + specular
    diffuse: np.ndarray  # (H, W, 3) float32 linear denoised diffuse (albedo re-applied)
    specular: np.ndarray | None  # (H, W, 3) linear specular: denoised, or the input passed through
    branches: tuple[str, ...]  # the branches whose network ran: ("diffuse",) or both
    specular_passed_through: bool  # the input had specular but no specular generator was given
    sanitized: dict[str, dict[str, int]] = field(default_factory=dict)  # layer -> nonzero repair counts
    nonfinite_outputs: int = 0  # network output values that were NaN/Inf (set to 0)
    tiles: int = 1  # network calls per branch
    network_seconds: float = 0.0  # generator time, synchronised (both branches)
    base_seconds: float = 0.0  # OIDN's time for a refiner's bases (0 for base "noisy")
    exposure_gain: float = 1.0  # the radiance went through the networks times this (exposure.py)
    dark_share: float = 0.0  # mean share of the second pass at DARK_GAIN x that (0: it did not run)
    resolved_share: float = 0.0  # mean weight of the input kept where it was resolved (resolved.py)
    seconds: float = 0.0  # whole call: sanitising, OIDN, transforms, networks, inverse

    @property
    def notes(self) -> list[str]:
        """Plain sentences for the user about what happened beyond the obvious."""
        notes = []
        for layer, counts in self.sanitized.items():
            what = ", ".join(f"{n} {kind}" for kind, n in counts.items())
            notes.append(f"{layer}: repaired {what} value(s) before denoising")
        if self.specular_passed_through:
            notes.append("specular: no specular network given, the noisy specular was added unchanged")
        if self.nonfinite_outputs:
            notes.append(f"the network produced {self.nonfinite_outputs} non-finite value(s), set to 0")
        if self.exposure_gain != 1.0:
            notes.append(f"a dim image: denoised at {self.exposure_gain:.3g}x its exposure, the output scaled back")
        if self.resolved_share:
            notes.append(
                f"where the render was already resolved, kept its detail (mean weight of the input "
                f"{self.resolved_share:.2g})"
            )
        return notes
