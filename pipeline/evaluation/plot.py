"""Error against time: the raw path tracer's curve and each denoiser's, relMSE over render + denoise seconds."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FixedLocator, FuncFormatter, LogLocator, NullFormatter, NullLocator

from admc.pipeline.evaluation.records import PATH_TRACER, EvalResult, denoising_methods, mean_curve
from admc.stores.atomic import publishing


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


def plot_error_vs_time(result: EvalResult, out_dir: Path) -> Path:
    fig = Figure(figsize=(6.4, 4.8))
    ax = fig.add_subplot()
    curves = {PATH_TRACER: mean_curve(result.path_tracer)}
    for method in denoising_methods(result):
        curves[method] = mean_curve([r for r in result.records if r.method == method])
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
