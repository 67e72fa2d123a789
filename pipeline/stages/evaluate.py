"""`admc-pipe eval`: the test split's full images through every denoiser, Table 1, plots, HTML page.

The stage builds the methods (noisy input, OIDN, OptiX where it runs, the learned model from each
weights file, named as Table 1's columns), runs the evaluation and renders the page from its result.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from admc.common.metrics import METRICS
from admc.errors import AdmcError, StageError
from admc.model.inference.options import DenoiserOptions
from admc.pipeline.config import Config
from admc.pipeline.evaluation import html, scoring
from admc.pipeline.evaluation.baselines import (
    Denoiser,
    NoisyInput,
    OidnDenoiser,
    OptixDenoiser,
    optix_unavailable_reason,
)
from admc.pipeline.evaluation.inputs import find_test_images
from admc.pipeline.evaluation.records import EvalResult, ScoredImage
from admc.pipeline.evaluation.table1 import build_table1
from admc.pipeline.render import backends as render
from admc.pipeline.render import scenes
from admc.pipeline.render.scenes import SceneSpec
from admc.pipeline.stages.corpus import corpus_splits
from admc.pipeline.stages.render import render_corpus
from admc.pipeline.weights import default_weights, load_model

REPORT_SCENES = 8  # scenes shown in the HTML page (every test image still counts in the tables)


class EvalStageError(AdmcError, RuntimeError):
    pass


@dataclass
class EvalOutcome:
    result: EvalResult
    report: Path
    scene_ids: list[str]


def eval_scenes(cfg: Config) -> list[SceneSpec]:
    """The corpus scenes assigned to the eval split (the same stable per-scene rule as tiling), and for
    the test split the dedicated test scenes: a fixed number per family, so every family is measured
    on enough images whatever the corpus size. The ood split is the out-of-family set alone."""
    if cfg.eval.split == "ood":
        return render.ood_corpus(cfg)
    corpus = render.corpus(cfg)
    splits = corpus_splits(cfg, corpus)
    chosen = [s for s in corpus if splits[s.scene_id] == cfg.eval.split]
    if cfg.eval.split == "test":
        families = list(cfg.eval.test_families)
        try:
            chosen += scenes.procedural_corpus(
                families, cfg.eval.test_scenes_per_family * len(families), cfg.eval.test_seed, cfg.eval.test_resolution
            )
        except scenes.SceneError as exc:
            raise EvalStageError(f"config key 'eval.test_families': {exc}") from None
    return chosen


def named_weights(specs: list[str]) -> list[tuple[str | None, Path]]:
    """[(column name, path)] from --weights values PATH or NAME=PATH. One unnamed file is named by the
    base it records (None here: "admc" or "admc+oidn"); several are "admc-<run>" after their run folder
    (or file stem), so ablations sit side by side in Table 1."""
    named = []
    for spec in specs:
        name, sep, rest = spec.partition("=")
        if not spec or (sep and not Path(spec).exists() and not (name and rest)):
            raise EvalStageError(
                f"--weights {spec!r}: give a weights file, PATH or NAME=PATH with both a column name and a file"
            )
        if sep and not Path(spec).exists():
            named.append((name, Path(rest)))
        else:
            path = Path(spec)
            label = path.parent.name if path.stem in ("weights-fp16", "checkpoint") else path.stem
            named.append((None if len(specs) == 1 else f"admc-{label}", path))
    names = [name for name, _ in named]
    if len(set(names)) != len(names):
        raise EvalStageError(f"the --weights columns would be named {names}; name them apart with NAME=PATH")
    return named


def default_models(cfg: Config) -> list[Path]:
    """The config's own model (`default_weights`: its finetune run, else pretrain run, else shipped
    weights), then the same for the other base where such weights exist: by default Table 1 shows
    admc and admc+oidn side by side."""
    other = cfg.tile.refiner_base if cfg.model.base == "noisy" else "noisy"
    paths = [default_weights(cfg)]
    try:
        paths.append(default_weights(replace(cfg, model=replace(cfg.model, base=other))))
    except StageError:
        pass
    return paths


ENSEMBLE_DARK = (4, True)
"""The costly settings eval.also_ensemble_dark adds a row for: the 4-way ensemble and the dark pass."""
ENSEMBLE_DARK_SUFFIX = "-ens4+dark"


def learned_denoisers(cfg: Config, weights: list[str] | None, device: str = "auto") -> list[Denoiser]:
    """The trained models, once per weights file (default: `default_models`), each named as its Table 1
    column; with eval.also_ensemble_dark each again with the 4-way ensemble and the dark pass, as its own
    row with its own time (unless eval.ensemble and eval.dark_pass are those already)."""
    named = named_weights(weights) if weights else [(None, path) for path in default_models(cfg)]
    settings = [(cfg.eval.ensemble, cfg.eval.dark_pass, "")]
    if cfg.eval.also_ensemble_dark and settings[0][:2] != ENSEMBLE_DARK:
        settings.append((*ENSEMBLE_DARK, ENSEMBLE_DARK_SUFFIX))
    models = []
    for name, path in named:
        for ensemble, dark_pass, suffix in settings:
            model = load_model(
                cfg,
                path,
                DenoiserOptions(
                    device=device,
                    name=name,
                    ensemble=ensemble,
                    dark_pass=dark_pass,
                    engine=cfg.eval.engine,
                    keep_resolved=cfg.eval.keep_resolved,
                ),
            )
            model.name += suffix
            models.append(model)
    return models


class ReportFigures:
    """evaluate()'s `on_image` for the HTML page: the figures of the first `limit` scenes, made while the
    float images are in memory and kept only as encoded PNGs (html.ReportGroup)."""

    def __init__(self, limit: int = REPORT_SCENES) -> None:
        self.limit = limit
        self.scene_ids: list[str] = []
        self.groups: list[html.ReportGroup] = []

    def __call__(self, scored: ScoredImage) -> None:
        if scored.scene_id not in self.scene_ids:
            if len(self.scene_ids) == self.limit:
                return
            self.scene_ids.append(scored.scene_id)
        metrics = {name: {m.label: getattr(scored.records[name], m.key) for m in METRICS} for name in scored.outputs}
        self.groups.append(
            html.report_group(
                html.ReportImage(scored.scene_id, scored.spp, scored.reference, dict(scored.outputs), metrics)
            )
        )


def optix_denoisers(setting: str) -> tuple[list[Denoiser], dict[str, str]]:
    """([OptiX] or [], {"optix": why it is absent}) for eval.optix = auto | on | off."""
    if setting == "off":
        return [], {"optix": "turned off (eval.optix = off)"}
    reason = optix_unavailable_reason()
    if reason is None:
        return [OptixDenoiser()], {}
    if setting == "on":
        raise EvalStageError(f"eval.optix = on, but {reason}; set eval.optix = auto to run without it")
    return [], {"optix": reason}


def scoring_config(cfg: Config) -> Config:
    """The config whose renders eval scores: its references at eval.reference_spp where that is set, else
    the val split's at render.val_reference_spp (the references its rows were cut from)."""
    spp = cfg.eval.reference_spp or (cfg.eval.split == "val" and cfg.render.val_reference_spp)
    if not spp:
        return cfg
    return replace(cfg, render=replace(cfg.render, reference_spp=spp))


def run_eval(cfg: Config, extra: list[Denoiser] = (), progress: bool = True) -> EvalOutcome:
    """Render the eval split's scenes if needed (cached), then evaluate noisy, OIDN, OptiX (where it
    runs) and `extra` denoisers (`learned_denoisers` for the trained model)."""
    optix, not_run = optix_denoisers(cfg.eval.optix)
    specs = eval_scenes(cfg)
    if not specs:
        none_built = " and eval.test_scenes_per_family is 0" if cfg.eval.split == "test" else ""
        raise EvalStageError(
            f"no scene of the corpus falls in the {cfg.eval.split!r} split "
            f"(tile.split = {list(cfg.tile.split)}){none_built}; add scenes or change tile.split"
        )
    scene_ids = [s.scene_id for s in specs]
    renders_dir = render_corpus(scoring_config(cfg), progress, specs).renders_dir
    images = find_test_images(renders_dir, scene_ids)
    oidn_routes = [OidnDenoiser(quality=cfg.eval.oidn_quality)]
    if cfg.eval.oidn_prefiltered:
        oidn_routes.append(OidnDenoiser(quality=cfg.eval.oidn_quality, prefiltered=True))
    denoisers = [NoisyInput(), *oidn_routes, *optix, *extra]
    out_dir = cfg.workdir_path(cfg.eval.out_dir)
    figures = ReportFigures()
    result = scoring.evaluate(
        images,
        denoisers,
        out_dir,
        progress=progress,
        repeats=cfg.eval.repeats,
        warmup=cfg.eval.warmup,
        not_run=not_run,
        on_image=figures,
    )
    devices = ", ".join(f"{name}: {device}" for name, device in result.devices.items())
    report = html.write_report(
        out_dir,
        title=f"admc evaluation: {len(scene_ids)} {cfg.eval.split} scenes",
        table=build_table1(result),
        metric_definitions={m.label: m.definition for m in METRICS},
        plots=[result.files["error_vs_time"]],
        groups=figures.groups,
        device=devices,
        notes=[f"{len(images)} test images; the page shows the first {REPORT_SCENES} scenes"],
    )
    return EvalOutcome(result, report, scene_ids)
