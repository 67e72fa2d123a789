"""The evaluation's files, each rendered from the result objects: per-image and Table 1 CSV, Table 1
Markdown, results.json, equal time, the error-against-time plot."""

from __future__ import annotations

import csv
import inspect
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from admc.common.metrics import METRICS, NONFINITE_RULE, reference_floor, ssim_floor
from admc.pipeline.evaluation.baselines import cpu_description
from admc.pipeline.evaluation.plot import plot_error_vs_time
from admc.pipeline.evaluation.records import (
    BEST_PERCENT_RULE,
    FLOOR_KEYS,
    FLOOR_RULE,
    PATH_TRACER,
    EvalResult,
    ImageRecord,
    denoising_methods,
    mean_curve,
)
from admc.pipeline.evaluation.table1 import build_table1, table1_markdown
from admc.stores.atomic import publishing, write_json

TIMING_RULE = (
    "denoise seconds = median of {repeats} timed run(s), each bracketed by the denoiser's synchronize(), "
    "after {warmup} warm-up run(s) of each denoiser per input layout (the first image with its layers' "
    "names and sizes); total seconds = the input's render time (from its sidecar) + denoise seconds; "
    "the path tracer's total is its render time alone."
)


def _write_text(path: Path, text: str) -> Path:
    with publishing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def _known(floor: float) -> float | None:
    """JSON has no NaN: a floor that is unknown (a reference without variance layers) is null."""
    return None if math.isnan(floor) else floor


def _floor_known(d: dict) -> dict:
    return {k: _known(v) if k in FLOOR_KEYS else v for k, v in d.items()}


def _record_dict(r: ImageRecord, out_dir: Path) -> dict:
    d = _floor_known(asdict(r))
    d["total_seconds"] = r.total_seconds
    d["relmse_minus_floor"] = _known(r.relmse_minus_floor)
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
    fields += [
        "denoise_seconds",
        "total_seconds",
        "nonfinite",
        "reference_floor",
        "relmse_minus_floor_avg",
        "ssim_floor",
    ]
    with publishing(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        for row in result.table:
            line = [row.spp, row.method, row.device, row.n_images]
            for m in METRICS:
                line += [repr(row.average[m.key]), repr(row.best_percent[m.key])]
            writer.writerow(
                line
                + [
                    repr(row.denoise_seconds),
                    repr(row.total_seconds),
                    row.nonfinite,
                    repr(row.reference_floor),
                    repr(row.relmse_minus_floor),
                    repr(row.ssim_floor),
                ]
            )
    return path


def _table_md(result: EvalResult, out_dir: Path) -> Path:
    return _write_text(out_dir / "table1.md", table1_markdown(build_table1(result)))


def equal_time(result: EvalResult) -> list[dict]:
    """Per denoiser and spp: the raw path tracer spp of nearest mean cost (log scale) and who wins on relMSE."""
    raw = mean_curve(result.path_tracer)
    raw_by_scene = {(r.scene_id, r.spp): r.relmse for r in result.path_tracer}
    rows = []
    for method in denoising_methods(result):
        mine = [r for r in result.records if r.method == method]
        for spp, (cost, err) in mean_curve(mine).items():
            raw_spp = min(raw, key=lambda s: abs(math.log(max(raw[s][0], 1e-12) / max(cost, 1e-12))))
            at_spp = [r for r in mine if r.spp == spp]
            wins = sum(r.relmse < raw_by_scene[(r.scene_id, raw_spp)] for r in at_spp)
            rows.append(
                {
                    "method": method,
                    "spp": spp,
                    "seconds": cost,
                    "relmse": err,
                    "raw_spp": raw_spp,
                    "raw_seconds": raw[raw_spp][0],
                    "raw_relmse": raw[raw_spp][1],
                    "beats_raw": err < raw[raw_spp][1],
                    "scenes_won": wins,
                    "scenes": len(at_spp),
                }
            )
    return rows


def error_at(curve: dict[int, tuple[float, float]], seconds: float) -> float | None:
    """The relMSE of a (spp -> (mean seconds, mean relMSE)) curve at `seconds`, interpolated linearly in log
    time and log error between its two neighbouring points (straight as in the log-log plot); None outside
    the curve's time range, where it would be a guess."""
    points = sorted(curve.values())
    times = [t for t, _ in points]
    if not times[0] <= seconds <= times[-1]:
        return None
    logs = np.log([max(e, 1e-30) for _, e in points])
    return float(np.exp(np.interp(math.log(seconds), np.log(times), logs)))


def equal_time_between(curves: dict[str, dict[int, tuple[float, float]]]) -> list[dict]:
    """For each denoiser's point (spp), every other denoiser's relMSE at the same mean total time (error_at),
    from their mean curves (records.mean_curve): who is better at equal cost, in both directions."""
    rows = []
    for method, curve in curves.items():
        for spp, (seconds, relmse) in curve.items():
            for other, other_curve in curves.items():
                if other == method:
                    continue
                theirs = error_at(other_curve, seconds)
                rows.append(
                    {
                        "method": method,
                        "spp": spp,
                        "seconds": seconds,
                        "relmse": relmse,
                        "other": other,
                        "other_relmse": theirs,
                        "ratio": None if theirs is None else relmse / theirs,
                    }
                )
    return rows


def _equal_time_md(rows: list[dict], between: list[dict], reference_cost: dict | None, out_dir: Path) -> Path:
    lines = [
        "# Equal time: denoised against the raw path tracer",
        "",
        "For each denoiser and input spp, the raw path tracer's spp whose mean cost is nearest "
        "(on a log scale) to the denoiser's mean cost (render + denoise), and whether the denoised "
        "image has the lower mean relMSE. Scenes won: scenes where the denoised image beats that "
        "raw render of the same scene.",
        "",
        *(
            [
                f"The references ({'/'.join(map(str, reference_cost['spp']))} spp, relMSE 0 by definition) "
                f"took {reference_cost['seconds']:.4g} s per scene on average.",
                "",
            ]
            if reference_cost
            else []
        ),
        "| denoiser | spp | seconds | relMSE | raw spp | raw seconds | raw relMSE | beats raw | scenes won |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['spp']} | {r['seconds']:.4g} | {r['relmse']:.4g} | {r['raw_spp']} | "
            f"{r['raw_seconds']:.4g} | {r['raw_relmse']:.4g} | {'yes' if r['beats_raw'] else 'no'} | "
            f"{r['scenes_won']}/{r['scenes']} |"
        )
    lines += [
        "",
        "# Equal time: denoiser against denoiser",
        "",
        "For each denoiser and input spp, every other denoiser's relMSE at the same mean cost (render + "
        "denoise), interpolated on its error-against-time curve (linearly in log time and log relMSE); "
        '"outside" where that cost lies outside its curve. Ratio below 1: the first denoiser is better '
        "at equal time.",
        "",
        "| denoiser | spp | seconds | relMSE | other | other's relMSE at these seconds | ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in between:
        theirs, ratio = (
            ("outside", "–") if r["other_relmse"] is None else (f"{r['other_relmse']:.4g}", f"{r['ratio']:.3f}")
        )
        lines.append(
            f"| {r['method']} | {r['spp']} | {r['seconds']:.4g} | {r['relmse']:.4g} | {r['other']} | "
            f"{theirs} | {ratio} |"
        )
    return _write_text(out_dir / "equal_time.md", "\n".join(lines) + "\n")


def write_outputs(result: EvalResult, out_dir: Path, repeats: int, warmup: int) -> dict[str, Path]:
    equal = equal_time(result)
    between = equal_time_between(
        {m: mean_curve([r for r in result.records if r.method == m]) for m in denoising_methods(result)}
    )
    files = {
        "per_image_csv": _write_per_image_csv(result, out_dir),
        "table1_csv": _table_csv(result, out_dir),
        "table1_md": _table_md(result, out_dir),
        "error_vs_time": plot_error_vs_time(result, out_dir),
        "equal_time": _equal_time_md(equal, between, result.reference_cost, out_dir),
        "results_json": out_dir / "results.json",
    }
    write_json(
        files["results_json"],
        {
            "metrics": {
                m.key: {"label": m.label, "lower_is_better": m.lower_is_better, "definition": m.definition}
                for m in METRICS
            },
            "nonfinite_rule": NONFINITE_RULE,
            "reference_floor": {
                "rule": FLOOR_RULE,
                "definition": inspect.getdoc(reference_floor),
                "per_scene": {r.scene_id: _known(r.reference_floor) for r in result.path_tracer},
            },
            "ssim_floor": {
                "definition": inspect.getdoc(ssim_floor),
                "per_scene": {r.scene_id: _known(r.ssim_floor) for r in result.path_tracer},
            },
            "best_percent_rule": BEST_PERCENT_RULE,
            "timing": {
                "repeats": repeats,
                "warmup": warmup,
                "rule": TIMING_RULE.format(repeats=repeats, warmup=warmup),
            },
            "devices": result.devices,
            "not_run": result.not_run,
            "weights": result.sources,
            "host": cpu_description(),
            "table": [_floor_known(asdict(row)) for row in result.table],
            "images": [_record_dict(r, out_dir) for r in result.records],
            "path_tracer": [_record_dict(r, out_dir) for r in result.path_tracer],
            "equal_time": equal,
            "equal_time_between_denoisers": between,
            "reference_cost": result.reference_cost,
            "scenes": [
                {
                    "scene_id": s.scene_id,
                    "reference": str(s.reference.relative_to(out_dir)),
                    "inputs": {str(k): str(v.relative_to(out_dir)) for k, v in s.inputs.items()},
                    "outputs": {
                        str(k): {m: str(p.relative_to(out_dir)) for m, p in v.items()} for k, v in s.outputs.items()
                    },
                }
                for s in result.scenes
            ],
        },
    )
    return files
