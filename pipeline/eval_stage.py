"""`admc-pipe eval`: the test split's full images through every denoiser, Table 1, plots, HTML page."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from admc.pipeline import evaluate, render, report_html, tile
from admc.pipeline.config import Config
from admc.pipeline.denoisers import Denoiser, NoisyInput, OidnDenoiser
from admc.pipeline.metrics import METRICS

REPORT_SCENES = 8  # scenes shown in the HTML page (every test image still counts in the tables)


class EvalStageError(RuntimeError):
    pass


@dataclass
class EvalOutcome:
    result: evaluate.EvalResult
    report: Path
    scene_ids: list[str]


def eval_scene_ids(cfg: Config) -> list[str]:
    """The corpus scenes assigned to the eval split (the same stable per-scene rule as tiling)."""
    return [s.scene_id for s in render.corpus(cfg)
            if tile.split_of(s.scene_id, cfg.tile.split, cfg.tile.seed) == cfg.eval.split]


def _report_images(result: evaluate.EvalResult) -> list[report_html.ReportImage]:
    metrics = {(r.scene_id, r.spp, r.method): {"1-SSIM": r.one_minus_ssim, "PSNR": r.psnr, "relMSE": r.relmse}
               for r in result.records}
    images = []
    for scene in result.scenes[:REPORT_SCENES]:
        reference = np.load(scene.reference)
        for spp, outputs in sorted(scene.outputs.items()):
            images.append(report_html.ReportImage(
                scene_id=scene.scene_id, spp=spp, reference=reference,
                outputs={name: np.load(path) for name, path in outputs.items()},
                metrics={name: metrics[(scene.scene_id, spp, name)] for name in outputs}))
    return images


def run_eval(cfg: Config, extra: list[Denoiser] = (), progress: bool = True) -> EvalOutcome:
    """Render the eval split's scenes if needed (cached), then evaluate noisy, OIDN and `extra` denoisers."""
    from admc.pipeline.stages import run_cached

    scene_ids = eval_scene_ids(cfg)
    if not scene_ids:
        raise EvalStageError(f"no scene of the corpus falls in the {cfg.eval.split!r} split "
                             f"(tile.split = {list(cfg.tile.split)}); add scenes or change tile.split")
    specs = [s for s in render.corpus(cfg) if s.scene_id in scene_ids]
    renders = render.render_tasks(cfg, specs)
    published, _ = run_cached(cfg, [t for levels in renders.values() for t in levels.values()], progress)
    renders_dir = render.link_renders(renders, published, Path(cfg.run.workdir) / "renders")
    images = evaluate.find_test_images(renders_dir, scene_ids)
    denoisers = [NoisyInput(), OidnDenoiser(quality=cfg.eval.oidn_quality), *extra]
    out_dir = cfg.workdir_path(cfg.eval.out_dir)
    result = evaluate.evaluate(images, denoisers, out_dir, progress=progress, repeats=cfg.eval.repeats,
                               warmup=cfg.eval.warmup)
    devices = ", ".join(f"{name}: {device}" for name, device in result.devices.items())
    report = report_html.write_report(
        out_dir, title=f"admc evaluation: {len(scene_ids)} {cfg.eval.split} scenes",
        table_markdown=result.files["table1_md"].read_text(),
        metric_definitions={m.label: m.definition for m in METRICS},
        plots=[result.files["error_vs_time"]], images=_report_images(result), device=devices,
        notes=[f"{len(images)} test images; the page shows the first {REPORT_SCENES} scenes"])
    return EvalOutcome(result, report, scene_ids)
