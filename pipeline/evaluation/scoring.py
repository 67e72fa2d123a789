"""Evaluation: run every denoiser on every test image, score it, write Table 1 and error against time.

Inputs are the render stage's folders (`<renders>/<scene>/spp0004.exr` + `.json`, `reference.exr`
+ `.json`; see inputs.py). Each noisy EXR and each reference is read once; every denoiser is timed on
it (`time_denoiser`) and scored with `metrics.METRICS` against the reference into an ImageRecord. The raw
path tracer (the noisy input, costing only its render time) is scored alongside as the curve the
denoisers must beat at equal time.

Every image is written as a float32 EXR a person opens in a viewer, `out_dir/images/<scene>/reference.exr`,
`spp0004_input.exr` and `spp0004_<denoiser>.exr`: the pixels that were scored, for every scene, so any
line of per_image.csv can be looked at or re-scored. The caller's `on_image` gets each test image's
float images while they are in memory (the eval stage makes the HTML page's figures from them); at most
one scene's images are held at a time, never the test set's. The tables are written by outputs.py.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn

from admc.common.buffers import BEAUTY
from admc.common.metrics import count_nonfinite, score
from admc.pipeline.evaluation.baselines import Denoiser, noisy_color, time_denoiser
from admc.pipeline.evaluation.inputs import by_scene, read_reference
from admc.pipeline.evaluation.outputs import write_outputs
from admc.pipeline.evaluation.records import (
    PATH_TRACER,
    EvalError,
    EvalResult,
    ImageRecord,
    ReferenceFloors,
    SceneImages,
    ScoredImage,
    TestImage,
    aggregate,
)
from admc.stores.exr import read_exr, write_exr

RESERVED_NAMES = frozenset({PATH_TRACER, "input", "reference"})
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")


def _check_denoisers(denoisers: list[Denoiser]) -> None:
    if not denoisers:
        raise EvalError("no denoisers to evaluate")
    names = [d.name for d in denoisers]
    for name in names:
        if name in RESERVED_NAMES or not NAME_PATTERN.fullmatch(name):
            raise EvalError(
                f"denoiser name {name!r} is reserved or not a plain file name "
                f"(letters, digits, . _ + -; not {', '.join(sorted(RESERVED_NAMES))})"
            )
    if len(set(names)) != len(names):
        raise EvalError(f"denoiser names must be unique, got {names}")


def _write(path: Path, image: np.ndarray) -> Path:
    """The image as a float32 EXR a person opens in any viewer: the pixels that were scored, bit for bit
    (half would round them, and refuses fireflies beyond 65504)."""
    write_exr(path, {BEAUTY: image}, precision="float")
    return path


@dataclass
class _Timing:
    """Times every denoiser by `time_denoiser`, warming each up once per input layout (its layers' names
    and sizes), not once per image. What a warm-up removes (JIT, oneDNN's primitives for a shape, the
    allocator's growth, OptiX's per-size denoiser) is paid once per layout; a warm-up run per image
    would double the evaluation's denoising time at the default single timed run."""

    repeats: int
    warmup: int
    warmed: set[tuple] = field(default_factory=set)

    def run(self, denoiser: Denoiser, layers: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
        layout = (denoiser.name, tuple(sorted((name, np.shape(layer)) for name, layer in layers.items())))
        warmup = 0 if layout in self.warmed else self.warmup
        self.warmed.add(layout)
        return time_denoiser(denoiser, layers, repeats=self.repeats, warmup=warmup)


def evaluate(
    images: list[TestImage],
    denoisers: list[Denoiser],
    out_dir: Path,
    progress: bool = True,
    repeats: int = 1,
    warmup: int = 1,
    not_run: dict[str, str] | None = None,
    on_image: Callable[[ScoredImage], None] | None = None,
) -> EvalResult:
    """Score every denoiser (and the raw path tracer) on every image; write the tables, plot and EXRs.

    `on_image` gets each test image's ScoredImage as soon as it is scored (the float images are
    dropped after it returns). `not_run` names methods the caller left out and why; the tables state
    it so a reader of the report does not mistake a missing column for a forgotten one."""
    _check_denoisers(denoisers)
    grouped = by_scene(images)
    out_dir = Path(out_dir)
    records, path_tracer, scenes = [], [], []
    timing = _Timing(repeats, warmup)
    with _ProgressBar(sum(len(g) for g in grouped.values()) * len(denoisers), progress) as bar:
        for scene_id, group in grouped.items():
            scene = SceneImages(scene_id, out_dir / "images" / scene_id / "reference.exr")
            for scored in _scene(group, scene, denoisers, bar, timing):
                path_tracer.append(scored.records[PATH_TRACER])
                records += [scored.records[d.name] for d in denoisers]
                if on_image is not None:
                    on_image(scored)
            del scored  # the scene's last images go before the next scene's are read
            scenes.append(scene)
    devices = {d.name: d.device for d in denoisers}
    table = aggregate(records, devices)
    sources = {d.name: d.source for d in denoisers if getattr(d, "source", None)}
    result = EvalResult(
        table, records, path_tracer, scenes, devices, {}, dict(not_run or {}), _reference_cost(images), sources
    )
    result.files = write_outputs(result, out_dir, repeats, warmup)
    return result


def _scene(
    group: list[TestImage], scene: SceneImages, denoisers: list[Denoiser], bar: tuple[Progress, TaskID], timing: _Timing
) -> Iterator[ScoredImage]:
    """One scene's test images by spp, each scored and written; the scene's paths go into `scene`. A
    generator, so only this scene's images are alive, one test image (and the reference) at a time."""
    reference, floors = read_reference(group[0].reference_path)
    _write(scene.reference, reference)
    for test in sorted(group, key=lambda t: t.spp):
        scored = _score(test, reference, floors, denoisers, scene.reference.parent, bar, timing)
        scene.inputs[test.spp] = scored.records[PATH_TRACER].image
        scene.outputs[test.spp] = {d.name: scored.records[d.name].image for d in denoisers}
        yield scored


def _score(
    test: TestImage,
    reference: np.ndarray,
    floors: ReferenceFloors,
    denoisers: list[Denoiser],
    folder: Path,
    bar: tuple[Progress, TaskID],
    timing: _Timing,
) -> ScoredImage:
    """One test image: the noisy input and every denoiser's output, each written to `folder` and scored."""
    layers = read_exr(test.noisy_path)
    noisy = noisy_color(layers)
    if noisy.shape != reference.shape:
        raise EvalError(
            f"{test.noisy_path}: image is {noisy.shape[:2]}, its reference "
            f"{test.reference_path} is {reference.shape[:2]}"
        )
    stem = f"spp{test.spp:04d}"
    records = {
        PATH_TRACER: _record(
            test,
            PATH_TRACER,
            "render (see sidecars)",
            noisy,
            reference,
            0.0,
            _write(folder / f"{stem}_input.exr", noisy),
            floors,
        )
    }
    outputs = {}
    progress, task = bar
    for denoiser in denoisers:
        progress.update(task, description=f"{denoiser.name} on {test.scene_id} @ {test.spp} spp")
        missing = getattr(denoiser, "missing_layers", lambda _: [])(layers)  # model.noise_input weights
        if missing:
            raise EvalError(
                f"{test.noisy_path}: lacks layer(s) {', '.join(missing)}, which {denoiser.name}'s "
                f"weights {getattr(denoiser, 'source', None)} read (model.noise_input: the variance of "
                "each pixel's mean, as `admc-pipe render` writes)"
            )
        image, seconds = timing.run(denoiser, layers)
        outputs[denoiser.name] = image
        records[denoiser.name] = _record(
            test,
            denoiser.name,
            denoiser.device,
            image,
            reference,
            seconds,
            _write(folder / f"{stem}_{denoiser.name}.exr", image),
            floors,
        )
        progress.advance(task)
    return ScoredImage(test.scene_id, test.spp, reference, noisy, outputs, records)


def _reference_cost(images: list[TestImage]) -> dict | None:
    """Mean render time of the scenes' references, the far end of the raw path tracer's curve."""
    per_scene = {t.scene_id: t for t in images}
    if not per_scene or any(not math.isfinite(t.reference_seconds) for t in per_scene.values()):
        return None
    return {
        "spp": sorted({t.reference_spp for t in per_scene.values()}),
        "seconds": float(np.mean([t.reference_seconds for t in per_scene.values()])),
    }


def _record(
    test: TestImage,
    method: str,
    device: str,
    image: np.ndarray,
    reference: np.ndarray,
    seconds: float,
    saved: Path,
    floors: ReferenceFloors,
) -> ImageRecord:
    return ImageRecord(
        test.scene_id,
        test.spp,
        method,
        device,
        **score(image, reference),
        nonfinite=count_nonfinite(image),
        render_seconds=test.render_seconds,
        denoise_seconds=seconds,
        image=saved,
        reference_floor=floors.relmse,
        ssim_floor=floors.one_minus_ssim,
    )


class _ProgressBar:
    """A rich progress bar on stderr, or nothing."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            disable=not enabled,
        )
        self.task = self.progress.add_task("evaluating", total=total)

    def __enter__(self) -> tuple[Progress, TaskID]:
        self.progress.start()
        return self.progress, self.task

    def __exit__(self, *exc) -> None:
        self.progress.stop()
