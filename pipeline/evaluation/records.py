"""What an evaluation produces, as data: one ImageRecord per (image, method), Table 1's rows, the result.

Every output (Markdown, CSV, JSON, the plot, the HTML page) is rendered from these objects; nothing is
parsed back from a file that was written. The float images themselves live only in a ScoredImage, one
test image at a time; what stays behind are the paths of the EXRs they were written to.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from admc.common.metrics import METRICS
from admc.errors import AdmcError
from admc.pipeline.evaluation.baselines import NoisyInput

PATH_TRACER = "path tracer"
TIE_RTOL, TIE_ATOL = 1e-6, 1e-12
BEST_PERCENT_RULE = (
    f"B.P. = share of the images of that spp on which a method has the best value of the metric. "
    f"Values within rtol {TIE_RTOL:g} (or atol {TIE_ATOL:g}) of the best are ties: each of the k tied "
    f"methods gets 1/k of that image's credit, so every spp/metric column sums to 100 %."
)
FLOOR_ROW = "reference floor"
FLOOR_KEYS = frozenset({"reference_floor", "relmse_minus_floor", "ssim_floor"})
FLOOR_COLUMN = "relMSE − floor"
FLOOR_RULE = (
    "The references are renders too: the reference floor row gives their own expected relMSE against the "
    "converged image (metrics.reference_floor) and, under 1-SSIM, about the 1-SSIM that the converged image "
    "itself would score against them (metrics.ssim_floor), both from their variance layers (NaN where a "
    "reference has none). Every relMSE above is measured against these references and so carries about this "
    "much of their noise; the relMSE − floor column subtracts it per image, an estimate of each method's "
    "error against the converged image (it can fall below 0 by chance). SSIM does not add up that way, but no "
    "method's 1-SSIM falls far below its floor: where the floor is most of a method's 1-SSIM, the column "
    "measures mostly the references' noise."
)


@dataclass(frozen=True)
class ReferenceFloors:
    """What a reference's own noise costs every method scored against it (NaN: no variance layers)."""

    relmse: float = math.nan  # metrics.reference_floor
    one_minus_ssim: float = math.nan  # metrics.ssim_floor


class EvalError(AdmcError, ValueError):
    """The test set or the denoisers cannot be evaluated as given."""


@dataclass(frozen=True)
class TestImage:
    """One noisy render to denoise and the reference it is scored against."""

    __test__ = False  # not a pytest test class

    scene_id: str
    spp: int
    noisy_path: Path
    reference_path: Path
    render_seconds: float
    reference_spp: int = 0  # 0: unknown
    reference_seconds: float = math.nan  # the reference's own render time: the raw curve's far end


@dataclass(frozen=True)
class ImageRecord:
    """Scores and cost of one method on one test image."""

    scene_id: str
    spp: int
    method: str
    device: str
    one_minus_ssim: float
    psnr: float
    relmse: float
    hdr_flip: float
    nonfinite: int  # NaN/inf values in the method's image, replaced by 0 before scoring
    render_seconds: float
    denoise_seconds: float
    image: Path  # the scored image as a float32 EXR (plain R, G, B), under out_dir/images/
    reference_floor: float = math.nan  # the reference's own expected relMSE (metrics.reference_floor)
    ssim_floor: float = math.nan  # the converged image's 1-SSIM against the reference (metrics.ssim_floor)

    @property
    def total_seconds(self) -> float:
        return self.render_seconds + self.denoise_seconds

    @property
    def relmse_minus_floor(self) -> float:
        """relMSE less the reference's own noise: an estimate of the error against the converged image."""
        return self.relmse - self.reference_floor


@dataclass(frozen=True)
class TableRow:
    """One line of Table 1: a method at one spp, averaged over the test images of that spp."""

    spp: int
    method: str
    device: str
    n_images: int
    average: dict[str, float]  # metric key -> mean over images
    best_percent: dict[str, float]  # metric key -> B.P. in percent
    denoise_seconds: float  # mean over images
    total_seconds: float  # mean over images
    nonfinite: int  # summed over images
    reference_floor: float = math.nan  # mean over images of the references' own expected relMSE
    relmse_minus_floor: float = math.nan  # mean over images of relMSE - reference floor
    ssim_floor: float = math.nan  # mean over images of the references' metrics.ssim_floor


@dataclass(frozen=True)
class ScoredImage:
    """One test image (a scene at one spp) just scored: its float images, handed to evaluate()'s `on_image`
    while they are in memory, so a caller makes figures without reading files back."""

    scene_id: str
    spp: int
    reference: np.ndarray  # (H, W, 3) float32 linear
    noisy: np.ndarray  # the path tracer's image (the denoisers' input colour)
    outputs: dict[str, np.ndarray]  # denoiser name -> its image, in the order evaluated
    records: dict[str, ImageRecord]  # PATH_TRACER and every denoiser name -> its scores


@dataclass
class SceneImages:
    """Where a person finds one scene's linear images: float32 EXRs, each the image as it was scored."""

    scene_id: str
    reference: Path
    inputs: dict[int, Path] = field(default_factory=dict)  # spp -> noisy input
    outputs: dict[int, dict[str, Path]] = field(default_factory=dict)  # spp -> method -> denoised


@dataclass
class EvalResult:
    table: list[TableRow]
    records: list[ImageRecord]  # every denoiser on every image
    path_tracer: list[ImageRecord]  # the noisy input of every image, costing its render time
    scenes: list[SceneImages]
    devices: dict[str, str]  # method -> device
    files: dict[str, Path]  # per_image_csv, results_json, table1_md, table1_csv, error_vs_time, equal_time
    not_run: dict[str, str] = field(default_factory=dict)  # method -> why it is absent (e.g. no CUDA for OptiX)
    reference_cost: dict | None = None  # {"spp": [...], "seconds": mean over scenes} when every sidecar has it
    sources: dict[str, str] = field(default_factory=dict)  # method -> weights file, for learned denoisers


def best_percent(per_image: list[dict[str, float]], lower_is_better: bool) -> dict[str, float]:
    """B.P. of each method in percent, from one {method: value} dict per image (BEST_PERCENT_RULE)."""
    methods = sorted({m for values in per_image for m in values})
    credit = dict.fromkeys(methods, 0.0)
    for values in per_image:
        best = min(values.values()) if lower_is_better else max(values.values())
        tied = [m for m, v in values.items() if math.isclose(v, best, rel_tol=TIE_RTOL, abs_tol=TIE_ATOL)]
        for m in tied:
            credit[m] += 1.0 / len(tied)
    return {m: 100.0 * c / len(per_image) for m, c in credit.items()}


def aggregate(records: list[ImageRecord], devices: dict[str, str]) -> list[TableRow]:
    """Table 1: per spp (ascending) and method (in `devices` order), averages and B.P. of every metric."""
    by_cell: dict[tuple[int, str], list[ImageRecord]] = defaultdict(list)
    for r in records:
        by_cell[(r.spp, r.method)].append(r)
    rows = []
    for spp in sorted({r.spp for r in records}):
        at_spp = [r for r in records if r.spp == spp]
        per_image: dict[str, dict[str, dict[str, float]]] = {m.key: defaultdict(dict) for m in METRICS}
        for r in at_spp:
            for m in METRICS:
                per_image[m.key][r.scene_id][r.method] = getattr(r, m.key)
        shares = {m.key: best_percent(list(per_image[m.key].values()), m.lower_is_better) for m in METRICS}
        for method in devices:
            cell = by_cell.get((spp, method), [])
            if not cell:
                continue
            rows.append(
                TableRow(
                    spp,
                    method,
                    devices[method],
                    len(cell),
                    {m.key: float(np.mean([getattr(r, m.key) for r in cell])) for m in METRICS},
                    {m.key: shares[m.key].get(method, 0.0) for m in METRICS},
                    float(np.mean([r.denoise_seconds for r in cell])),
                    float(np.mean([r.total_seconds for r in cell])),
                    sum(r.nonfinite for r in cell),
                    float(np.mean([r.reference_floor for r in cell])),
                    float(np.mean([r.relmse_minus_floor for r in cell])),
                    float(np.mean([r.ssim_floor for r in cell])),
                )
            )
    return rows


def mean_curve(records: list[ImageRecord]) -> dict[int, tuple[float, float]]:
    """spp -> (mean total seconds, mean relMSE) over the scenes."""
    by_spp: dict[int, list[ImageRecord]] = defaultdict(list)
    for r in records:
        by_spp[r.spp].append(r)
    return {
        spp: (float(np.mean([r.total_seconds for r in rs])), float(np.mean([r.relmse for r in rs])))
        for spp, rs in sorted(by_spp.items())
    }


def denoising_methods(result: EvalResult) -> list[str]:
    """Methods that change the image: the noisy-input row is the path tracer's own curve already."""
    return [m for m in result.devices if m != NoisyInput.name]
