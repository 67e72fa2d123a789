"""Evaluation: run every denoiser on every test image, score it, write Table 1 and error against time.

Inputs are the render stage's folders (`<renders>/<scene>/spp0004.exr` + `.json`, `reference.exr`
+ `.json`). Each noisy EXR and each reference is read once; every denoiser is timed on it
(`time_denoiser`), scored with `metrics.METRICS` against the reference, and its image is saved under
`out_dir/images/` so the report can show it without this process holding every image in memory.
The raw path tracer (the noisy input, costing only its render time) is scored alongside as the
curve the denoisers must beat at equal time.
"""
from __future__ import annotations

import csv
import inspect
import json
import math
import re
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FixedLocator, FuncFormatter, LogLocator, NullFormatter, NullLocator
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from admc.errors import AdmcError
from admc.pipeline.evaluation.baselines import Denoiser, NoisyInput, cpu_description, noisy_color, time_denoiser
from admc.common.metrics import METRICS, NONFINITE_RULE, count_nonfinite, reference_floor, score
from admc.stores.atomic import publishing, write_json
from admc.stores.exr import exr_layers, read_exr

PATH_TRACER = "path tracer"
RESERVED_NAMES = frozenset({PATH_TRACER, "input", "reference"})
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")
TIE_RTOL, TIE_ATOL = 1e-6, 1e-12
BEST_PERCENT_RULE = (
    f"B.P. = share of the images of that spp on which a method has the best value of the metric. "
    f"Values within rtol {TIE_RTOL:g} (or atol {TIE_ATOL:g}) of the best are ties: each of the k tied "
    f"methods gets 1/k of that image's credit, so every spp/metric column sums to 100 %.")
FLOOR_ROW = "reference floor"
FLOOR_KEYS = frozenset({"reference_floor", "relmse_minus_floor"})
FLOOR_COLUMN = "relMSE − floor"
FLOOR_RULE = ("The references are renders too: the reference floor row is their own expected relMSE against the "
              "converged image (metrics.reference_floor, from their variance layers; NaN where a reference has "
              "none). Every relMSE above is measured against these references and so carries about this much "
              "of their noise; the relMSE − floor column subtracts it per image, an estimate of each method's "
              "error against the converged image (it can fall below 0 by chance).")
TIMING_RULE = ("denoise seconds = median of {repeats} runs after {warmup} warm-up run(s), each bracketed by "
               "the denoiser's synchronize(); total seconds = the input's render time (from its sidecar) "
               "+ denoise seconds; the path tracer's total is its render time alone.")


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
    reference_spp: int = 0                 # 0: unknown
    reference_seconds: float = math.nan    # the reference's own render time: the raw curve's far end


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
    nonfinite: int            # NaN/inf values in the method's image, replaced by 0 before scoring
    render_seconds: float
    denoise_seconds: float
    image: Path               # .npy of the (H, W, 3) float32 linear image
    reference_floor: float = math.nan  # the reference's own expected relMSE (metrics.reference_floor)

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
    average: dict[str, float]        # metric key -> mean over images
    best_percent: dict[str, float]   # metric key -> B.P. in percent
    denoise_seconds: float           # mean over images
    total_seconds: float             # mean over images
    nonfinite: int                   # summed over images
    reference_floor: float = math.nan       # mean over images of the references' own expected relMSE
    relmse_minus_floor: float = math.nan    # mean over images of relMSE - reference floor


@dataclass
class SceneImages:
    """Where the report finds one scene's linear images (float32 .npy, (H, W, 3))."""
    scene_id: str
    reference: Path
    inputs: dict[int, Path] = field(default_factory=dict)                 # spp -> noisy input
    outputs: dict[int, dict[str, Path]] = field(default_factory=dict)     # spp -> method -> denoised


@dataclass
class EvalResult:
    table: list[TableRow]
    records: list[ImageRecord]        # every denoiser on every image
    path_tracer: list[ImageRecord]    # the noisy input of every image, costing its render time
    scenes: list[SceneImages]
    devices: dict[str, str]           # method -> device
    files: dict[str, Path]            # per_image_csv, results_json, table1_md, table1_csv, error_vs_time, equal_time
    not_run: dict[str, str] = field(default_factory=dict)  # method -> why it is absent (e.g. no CUDA for OptiX)
    reference_cost: dict | None = None  # {"spp": [...], "seconds": mean over scenes} when every sidecar has it
    sources: dict[str, str] = field(default_factory=dict)  # method -> weights file, for learned denoisers


# ---------------------------------------------------------------------------------------------- inputs

def _sidecar(path: Path, scene_id: str, reference: bool) -> dict:
    if not path.is_file():
        raise EvalError(f"{path}: sidecar missing (or a dangling link): render the scene again")
    try:
        side = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise EvalError(f"{path}: sidecar is not valid JSON ({exc})") from None
    missing = [k for k in ("scene_id", "spp", "reference", "render_seconds") if k not in side]
    if missing:
        raise EvalError(f"{path}: sidecar lacks {', '.join(missing)}")
    if side["scene_id"] != scene_id or bool(side["reference"]) != reference:
        raise EvalError(f"{path}: sidecar is for scene {side['scene_id']!r} (reference={side['reference']}), "
                        f"expected {scene_id!r} (reference={reference})")
    return side


def find_test_images(renders_dir: Path, scene_ids: list[str] | None = None) -> list[TestImage]:
    """Every noisy render of the given scenes (default: every scene folder), sorted by scene then spp."""
    renders_dir = Path(renders_dir)
    if not renders_dir.is_dir():
        raise EvalError(f"{renders_dir}: no renders folder (run `admc-pipe render` first)")
    if scene_ids is None:
        folders = sorted(p for p in renders_dir.iterdir() if p.is_dir())
    else:
        folders = [renders_dir / s for s in scene_ids]
    if not folders:
        raise EvalError(f"{renders_dir}: no scene folders to evaluate")
    images = []
    for folder in folders:
        if not folder.is_dir():
            raise EvalError(f"{folder}: no such scene folder")
        reference = folder / "reference.exr"
        if not reference.is_file():
            raise EvalError(f"{folder}: reference.exr missing (or a dangling link): render the scene again")
        ref_side = _sidecar(folder / "reference.json", folder.name, reference=True)
        noisy = sorted(folder.glob("spp*.exr"))
        if not noisy:
            raise EvalError(f"{folder}: no noisy renders (spp*.exr)")
        for path in noisy:
            side = _sidecar(path.with_suffix(".json"), folder.name, reference=False)
            images.append(TestImage(folder.name, int(side["spp"]), path, reference, float(side["render_seconds"]),
                                    int(ref_side.get("spp", 0)), float(ref_side["render_seconds"])))
    return sorted(images, key=lambda t: (t.scene_id, t.spp))


def _reference(path: Path) -> tuple[np.ndarray, float]:
    """(diffuse + specular, its reference floor) of a reference EXR; the floor is NaN where the file has
    no variance layers (a reference rendered elsewhere)."""
    present = exr_layers(path)
    layers = read_exr(path, [name for name in ("diffuse", "specular", "diffuse_var", "specular_var") if name in present])
    radiance = noisy_color(layers)
    variances = [layers[name] for name in ("diffuse_var", "specular_var") if name in layers]
    return radiance, reference_floor(sum(variances), radiance) if variances else math.nan


def _check_denoisers(denoisers: list[Denoiser]) -> None:
    if not denoisers:
        raise EvalError("no denoisers to evaluate")
    names = [d.name for d in denoisers]
    for name in names:
        if name in RESERVED_NAMES or not NAME_PATTERN.fullmatch(name):
            raise EvalError(f"denoiser name {name!r} is reserved or not a plain file name "
                            f"(letters, digits, . _ + -; not {', '.join(sorted(RESERVED_NAMES))})")
    if len(set(names)) != len(names):
        raise EvalError(f"denoiser names must be unique, got {names}")


def _by_scene(images: list[TestImage]) -> dict[str, list[TestImage]]:
    if not images:
        raise EvalError("no test images to evaluate")
    grouped: dict[str, list[TestImage]] = defaultdict(list)
    for image in images:
        grouped[image.scene_id].append(image)
    for scene_id, group in grouped.items():
        if len({t.reference_path for t in group}) != 1:
            raise EvalError(f"scene {scene_id!r}: its images name different references")
        if len({t.spp for t in group}) != len(group):
            raise EvalError(f"scene {scene_id!r}: more than one image at the same spp")
    return grouped


def _save(path: Path, image: np.ndarray) -> Path:
    with publishing(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(image, dtype=np.float32))
    return path


# ---------------------------------------------------------------------------------------------- running

def evaluate(images: list[TestImage], denoisers: list[Denoiser], out_dir: Path, progress: bool = True,
             repeats: int = 3, warmup: int = 1, not_run: dict[str, str] | None = None) -> EvalResult:
    """Score every denoiser (and the raw path tracer) on every image; write the tables, plot and files.

    `not_run` names methods the caller left out and why; the tables state it so a reader of the
    report does not mistake a missing column for a forgotten one."""
    _check_denoisers(denoisers)
    grouped = _by_scene(images)
    out_dir = Path(out_dir)
    records, path_tracer, scenes = [], [], []
    with _ProgressBar(sum(len(g) for g in grouped.values()) * len(denoisers), progress) as (bar, task):
        for scene_id, group in grouped.items():
            folder = out_dir / "images" / scene_id
            reference, floor = _reference(group[0].reference_path)
            scene = SceneImages(scene_id, _save(folder / "reference.npy", reference))
            for test in sorted(group, key=lambda t: t.spp):
                layers = read_exr(test.noisy_path)
                noisy = noisy_color(layers)
                if noisy.shape != reference.shape:
                    raise EvalError(f"{test.noisy_path}: image is {noisy.shape[:2]}, its reference "
                                    f"{test.reference_path} is {reference.shape[:2]}")
                scene.inputs[test.spp] = _save(folder / f"spp{test.spp:04d}_input.npy", noisy)
                path_tracer.append(_record(test, PATH_TRACER, "render (see sidecars)", noisy, reference, 0.0,
                                           scene.inputs[test.spp], floor))
                for denoiser in denoisers:
                    bar.update(task, description=f"{denoiser.name} on {scene_id} @ {test.spp} spp")
                    image, seconds = time_denoiser(denoiser, layers, repeats=repeats, warmup=warmup)
                    saved = _save(folder / f"spp{test.spp:04d}_{denoiser.name}.npy", image)
                    scene.outputs.setdefault(test.spp, {})[denoiser.name] = saved
                    records.append(_record(test, denoiser.name, denoiser.device, image, reference, seconds, saved,
                                           floor))
                    bar.advance(task)
            scenes.append(scene)
    devices = {d.name: d.device for d in denoisers}
    table = aggregate(records, devices)
    sources = {d.name: d.source for d in denoisers if getattr(d, "source", None)}
    result = EvalResult(table, records, path_tracer, scenes, devices, {}, dict(not_run or {}),
                        _reference_cost(images), sources)
    result.files = _write_outputs(result, out_dir, repeats, warmup)
    return result


def _reference_cost(images: list[TestImage]) -> dict | None:
    """Mean render time of the scenes' references, the far end of the raw path tracer's curve."""
    per_scene = {t.scene_id: t for t in images}
    if not per_scene or any(not math.isfinite(t.reference_seconds) for t in per_scene.values()):
        return None
    return {"spp": sorted({t.reference_spp for t in per_scene.values()}),
            "seconds": float(np.mean([t.reference_seconds for t in per_scene.values()]))}


def _record(test: TestImage, method: str, device: str, image: np.ndarray, reference: np.ndarray,
            seconds: float, saved: Path, floor: float) -> ImageRecord:
    return ImageRecord(test.scene_id, test.spp, method, device, **score(image, reference),
                       nonfinite=count_nonfinite(image), render_seconds=test.render_seconds,
                       denoise_seconds=seconds, image=saved, reference_floor=floor)


class _ProgressBar:
    """A rich progress bar on stderr, or nothing."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), disable=not enabled)
        self.task = self.progress.add_task("evaluating", total=total)

    def __enter__(self):
        self.progress.start()
        return self.progress, self.task

    def __exit__(self, *exc) -> None:
        self.progress.stop()


# ---------------------------------------------------------------------------------------------- tables

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
            rows.append(TableRow(
                spp, method, devices[method], len(cell),
                {m.key: float(np.mean([getattr(r, m.key) for r in cell])) for m in METRICS},
                {m.key: shares[m.key].get(method, 0.0) for m in METRICS},
                float(np.mean([r.denoise_seconds for r in cell])), float(np.mean([r.total_seconds for r in cell])),
                sum(r.nonfinite for r in cell), float(np.mean([r.reference_floor for r in cell])),
                float(np.mean([r.relmse_minus_floor for r in cell]))))
    return rows


def _mean_curve(records: list[ImageRecord]) -> dict[int, tuple[float, float]]:
    """spp -> (mean total seconds, mean relMSE) over the scenes."""
    by_spp: dict[int, list[ImageRecord]] = defaultdict(list)
    for r in records:
        by_spp[r.spp].append(r)
    return {spp: (float(np.mean([r.total_seconds for r in rs])), float(np.mean([r.relmse for r in rs])))
            for spp, rs in sorted(by_spp.items())}


# ---------------------------------------------------------------------------------------------- outputs

def _write_text(path: Path, text: str) -> Path:
    with publishing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def _floor_known(d: dict) -> dict:
    """JSON has no NaN: a floor that is unknown (a reference without variance layers) is null."""
    return {k: None if k in FLOOR_KEYS and math.isnan(v) else v for k, v in d.items()}


def _record_dict(r: ImageRecord, out_dir: Path) -> dict:
    d = _floor_known(asdict(r))
    d["total_seconds"] = r.total_seconds
    d["relmse_minus_floor"] = None if math.isnan(r.relmse_minus_floor) else r.relmse_minus_floor
    d["image"] = str(r.image.relative_to(out_dir))
    return d


def _write_per_image_csv(result: EvalResult, out_dir: Path) -> Path:
    rows = [_record_dict(r, out_dir) for r in result.path_tracer + result.records]
    rows.sort(key=lambda d: (d["scene_id"], d["spp"], d["method"] != PATH_TRACER))
    path = out_dir / "per_image.csv"
    with publishing(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def _table_csv(result: EvalResult, out_dir: Path) -> Path:
    path = out_dir / "table1.csv"
    fields = ["spp", "denoiser", "device", "n_images"]
    for m in METRICS:
        fields += [f"{m.key}_avg", f"{m.key}_bp"]
    fields += ["denoise_seconds", "total_seconds", "nonfinite", "reference_floor", "relmse_minus_floor_avg"]
    with publishing(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        for row in result.table:
            line = [row.spp, row.method, row.device, row.n_images]
            for m in METRICS:
                line += [repr(row.average[m.key]), repr(row.best_percent[m.key])]
            writer.writerow(line + [repr(row.denoise_seconds), repr(row.total_seconds), row.nonfinite,
                                    repr(row.reference_floor), repr(row.relmse_minus_floor)])
    return path


def _table_md(result: EvalResult, out_dir: Path) -> Path:
    head = ["spp", "Denoiser"] + [f"{m.label} {'↓' if m.lower_is_better else '↑'} {part}"
                                  for m in METRICS for part in ("Avg.", "B.P.")] + [f"{FLOOR_COLUMN} ↓ Avg."]
    lines = ["# Table 1: aggregate results over the test images", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for spp in sorted({row.spp for row in result.table}):
        rows = [row for row in result.table if row.spp == spp]
        best = {m.key: (min if m.lower_is_better else max)(row.average[m.key] for row in rows) for m in METRICS}
        top = {m.key: max(row.best_percent[m.key] for row in rows) for m in METRICS}
        unbiased = min(row.relmse_minus_floor for row in rows)
        for i, row in enumerate(rows):
            cells = [str(spp) if i == 0 else "", row.method]
            for m in METRICS:
                avg = f"{row.average[m.key]:.4f}"
                bp = f"{row.best_percent[m.key]:.2f}%"
                cells.append(f"**{avg}**" if row.average[m.key] == best[m.key] else avg)
                cells.append(f"**{bp}**" if row.best_percent[m.key] == top[m.key] else bp)
            value = f"{row.relmse_minus_floor:.4f}"
            cells.append(f"**{value}**" if row.relmse_minus_floor == unbiased else value)
            lines.append("| " + " | ".join(cells) + " |")
        floor = f"{rows[0].reference_floor:.4f}"  # every method at one spp is scored against the same references
        cells = ["", FLOOR_ROW] + [c for m in METRICS for c in ((floor, "–") if m.key == "relmse" else ("–", "–"))]
        lines.append("| " + " | ".join(cells + ["–"]) + " |")
    counts = ", ".join(f"{spp} spp: {n}" for spp, n in
                       sorted({(row.spp, row.n_images) for row in result.table}))
    lines += ["", f"Images per spp: {counts}. Best average and highest B.P. in bold.", "",
              "**B.P.** " + BEST_PERCENT_RULE + " Shown rounded to 2 decimals.", "",
              f"**{FLOOR_ROW}** " + FLOOR_RULE, "",
              "**Devices:** " + "; ".join(f"{name}: {dev}" for name, dev in result.devices.items()), "",
              *(["**Weights:** " + "; ".join(f"{name}: {path}" for name, path in result.sources.items()), ""]
                if result.sources else []),
              *(["**Not run:** " + "; ".join(f"{name}: {why}" for name, why in result.not_run.items()), ""]
                if result.not_run else []),
              "**Non-finite values** " + NONFINITE_RULE + " " + _nonfinite_summary(result), "",
              "## Metric definitions", ""]
    for m in METRICS:
        lines += [f"**{m.label}**: " + " ".join(m.definition.split()), ""]
    return _write_text(out_dir / "table1.md", "\n".join(lines))


def _nonfinite_summary(result: EvalResult) -> str:
    counts = defaultdict(int)
    for r in result.path_tracer:
        counts["noisy inputs"] += r.nonfinite
    for r in result.records:
        counts[r.method] += r.nonfinite
    return "Counted: " + ", ".join(f"{name} {n}" for name, n in counts.items()) + "."


def _readable_log_ticks(axis, values: list[float]) -> None:
    """Plain-number tick labels a reader can interpolate: under one decade of data, five ticks spread
    over the data; up to three decades, 1-2-5 steps; beyond, matplotlib's decades."""
    positive = [v for v in values if v > 0]
    if positive and max(positive) < 10 * min(positive):
        axis.set_major_locator(FixedLocator(np.geomspace(min(positive), max(positive), 5)))
        axis.set_minor_locator(NullLocator())
    elif positive and max(positive) < 1000 * min(positive):
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
    axis.set_minor_formatter(NullFormatter())


def _plot(result: EvalResult, out_dir: Path) -> Path:
    fig = Figure(figsize=(6.4, 4.8))
    ax = fig.add_subplot()
    curves = {PATH_TRACER: _mean_curve(result.path_tracer)}
    for method in _denoising_methods(result):
        curves[method] = _mean_curve([r for r in result.records if r.method == method])
    for method, curve in curves.items():
        xs, ys = zip(*curve.values())
        style = {"color": "black", "linestyle": "--", "zorder": 3} if method == PATH_TRACER else {}
        ax.plot(xs, ys, marker="o", label=method, **style)
        for spp, (x, y) in curve.items():
            ax.annotate(f"{spp}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    points = [point for curve in curves.values() for point in curve.values()]
    xs = [p[0] for p in points]
    if result.reference_cost:  # its error is 0 by definition, so it is a cost line, not a point
        seconds = result.reference_cost["seconds"]
        spp = "/".join(str(s) for s in result.reference_cost["spp"])
        ax.axvline(seconds, color="gray", linestyle=":", label=f"reference render ({spp} spp)")
        xs.append(seconds)
    floor = float(np.mean([r.reference_floor for r in result.path_tracer]))
    if math.isfinite(floor) and floor > 0:  # below it, differences are the reference's noise
        ax.axhline(floor, color="gray", linestyle="-.", label="reference floor")
        points.append((xs[0], floor))
    for axis, values in ((ax.xaxis, xs), (ax.yaxis, [p[1] for p in points])):
        _readable_log_ticks(axis, values)
    ax.set_xlabel("seconds (render + denoise), mean over scenes")
    ax.set_ylabel("relMSE, mean over scenes")
    ax.set_title("Error against time (points labelled with spp)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = out_dir / "error_vs_time.png"
    with publishing(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    return path


def _denoising_methods(result: EvalResult) -> list[str]:
    """Methods that change the image: the noisy-input row is the path tracer's own curve already."""
    return [m for m in result.devices if m != NoisyInput.name]


def equal_time(result: EvalResult) -> list[dict]:
    """Per denoiser and spp: the raw path tracer spp of nearest mean cost (log scale) and who wins on relMSE."""
    raw = _mean_curve(result.path_tracer)
    raw_by_scene = {(r.scene_id, r.spp): r.relmse for r in result.path_tracer}
    rows = []
    for method in _denoising_methods(result):
        mine = [r for r in result.records if r.method == method]
        for spp, (cost, err) in _mean_curve(mine).items():
            raw_spp = min(raw, key=lambda s: abs(math.log(max(raw[s][0], 1e-12) / max(cost, 1e-12))))
            at_spp = [r for r in mine if r.spp == spp]
            wins = sum(r.relmse < raw_by_scene[(r.scene_id, raw_spp)] for r in at_spp)
            rows.append({"method": method, "spp": spp, "seconds": cost, "relmse": err, "raw_spp": raw_spp,
                         "raw_seconds": raw[raw_spp][0], "raw_relmse": raw[raw_spp][1],
                         "beats_raw": err < raw[raw_spp][1], "scenes_won": wins, "scenes": len(at_spp)})
    return rows


def _equal_time_md(rows: list[dict], reference_cost: dict | None, out_dir: Path) -> Path:
    lines = ["# Equal time: denoised against the raw path tracer", "",
             "For each denoiser and input spp, the raw path tracer's spp whose mean cost is nearest "
             "(on a log scale) to the denoiser's mean cost (render + denoise), and whether the denoised "
             "image has the lower mean relMSE. Scenes won: scenes where the denoised image beats that "
             "raw render of the same scene.", "",
             *([f"The references ({'/'.join(map(str, reference_cost['spp']))} spp, relMSE 0 by definition) "
                f"took {reference_cost['seconds']:.4g} s per scene on average.", ""] if reference_cost else []),
             "| denoiser | spp | seconds | relMSE | raw spp | raw seconds | raw relMSE | beats raw | scenes won |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['spp']} | {r['seconds']:.4g} | {r['relmse']:.4g} | {r['raw_spp']} | "
                     f"{r['raw_seconds']:.4g} | {r['raw_relmse']:.4g} | {'yes' if r['beats_raw'] else 'no'} | "
                     f"{r['scenes_won']}/{r['scenes']} |")
    return _write_text(out_dir / "equal_time.md", "\n".join(lines) + "\n")


def _write_outputs(result: EvalResult, out_dir: Path, repeats: int, warmup: int) -> dict[str, Path]:
    equal = equal_time(result)
    files = {"per_image_csv": _write_per_image_csv(result, out_dir), "table1_csv": _table_csv(result, out_dir),
             "table1_md": _table_md(result, out_dir), "error_vs_time": _plot(result, out_dir),
             "equal_time": _equal_time_md(equal, result.reference_cost, out_dir), "results_json": out_dir / "results.json"}
    write_json(files["results_json"], {
        "metrics": {m.key: {"label": m.label, "lower_is_better": m.lower_is_better, "definition": m.definition}
                    for m in METRICS},
        "nonfinite_rule": NONFINITE_RULE,
        "reference_floor": {"rule": FLOOR_RULE, "definition": inspect.getdoc(reference_floor),
                            "per_scene": {r.scene_id: _floor_known({"reference_floor": r.reference_floor})["reference_floor"]
                                          for r in result.path_tracer}},
        "best_percent_rule": BEST_PERCENT_RULE,
        "timing": {"repeats": repeats, "warmup": warmup, "rule": TIMING_RULE.format(repeats=repeats, warmup=warmup)},
        "devices": result.devices,
        "not_run": result.not_run,
        "weights": result.sources,
        "host": cpu_description(),
        "table": [_floor_known(asdict(row)) for row in result.table],
        "images": [_record_dict(r, out_dir) for r in result.records],
        "path_tracer": [_record_dict(r, out_dir) for r in result.path_tracer],
        "equal_time": equal,
        "reference_cost": result.reference_cost,
        "scenes": [{"scene_id": s.scene_id, "reference": str(s.reference.relative_to(out_dir)),
                    "inputs": {str(k): str(v.relative_to(out_dir)) for k, v in s.inputs.items()},
                    "outputs": {str(k): {m: str(p.relative_to(out_dir)) for m, p in v.items()}
                                for k, v in s.outputs.items()}} for s in result.scenes],
    })
    return files
