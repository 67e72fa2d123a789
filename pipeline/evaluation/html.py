"""The evaluation report as one self-contained HTML file a person opens in any browser, offline.

Everything is inside index.html: images and plots as base64 PNG data URIs, CSS and a little vanilla
JS inline (the page, its CSS and JS are the package files in templates/), no fonts or scripts from
the network, so the file can be mailed or archived as is. Table 1 comes as a Table1 object; each image
comparison as a ReportGroup, which `report_group` encodes while the caller still holds the float images.

Display rules (also printed on the page):
- images are tone-mapped with clip(max(x, 0)^(1/2.2)) to 8 bit, no exposure change: the same display
  mapping the PSNR/SSIM metrics use, so what you see is what was scored;
- heat maps show the per-pixel relative squared error mean_c (x - ref)^2 / (ref^2 + 0.01) on a
  log10 colour scale from 1e-5 to 1e2 (fixed, so every heat map of the report is comparable);
- NaN/Inf pixels are painted magenta in images and heat maps and counted in the notes;
- images larger than 1280x720 are box-filtered in linear space to fit inside 1280x720 before
  embedding (keeps the file size sane); the zoom then magnifies those embedded pixels. Up to that
  size the embedded PNG is the full-resolution image, the overview thumbnails are the same PNG
  scaled by the browser, and the zoom crops it pixel for pixel.
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass
from datetime import datetime
from importlib import resources
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from PIL import Image

from admc.pipeline.evaluation.table1 import Cell, Table1

from admc.common.metrics import GAMMA, RELMSE_EPS as HEAT_EPS, to_ldr  # one definition: heat maps show relMSE per pixel

MAX_EMBED = (1280, 720)  # (width, height) of the largest image embedded at full resolution
THUMB = (240, 240)  # (width, height) box the overview thumbnails fit into
THUMB_MIN = 16  # thinnest thumbnail side in CSS pixels (stretched beyond the aspect)
HEAT_LOG10_RANGE = (-5.0, 2.0)  # colour scale ends of the heat maps, in decades
HEAT_COLORMAP = "inferno"
MAGENTA = (255, 0, 255)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass
class ReportImage:
    """One scene at one spp: its reference and every denoiser's output (including "noisy")."""

    scene_id: str
    spp: int
    reference: np.ndarray  # (H, W, 3) float32 linear HDR
    outputs: dict[str, np.ndarray]  # denoiser name -> (H, W, 3) linear HDR; includes "noisy"
    metrics: dict[str, dict[str, float]]  # denoiser name -> {"1-SSIM": .., "PSNR": .., "relMSE": ..}


@dataclass(frozen=True)
class ReportGroup:
    """One ReportImage as the page shows it: its figures with the PNGs encoded, and its NaN/Inf notes.
    Small, so a caller keeps these instead of the float images they were made from."""

    body: str
    notes: tuple[str, ...]


def write_report(
    out_dir: Path,
    *,
    title: str,
    table: Table1,
    metric_definitions: dict[str, str],
    plots: list[Path],
    groups: list[ReportGroup],
    device: str,
    notes: list[str] = (),
) -> Path:
    """Write out_dir/index.html and return its path. Table 1 and the plots come first (readers come for
    them), then the metric definitions and notes, then the `report_group` image comparisons with zoom."""
    notes = list(notes) + [note for group in groups for note in group.notes]
    page = _template("report.html").format(
        title=_esc(title),
        device=_esc(device),
        date=_esc(datetime.now().astimezone().isoformat(timespec="seconds")),
        definitions="\n".join(f"<dt>{_esc(k)}</dt><dd>{_esc(v)}</dd>" for k, v in metric_definitions.items()),
        display_rules=_DISPLAY_RULES,
        notes="\n".join(f"<li>{_esc(n)}</li>" for n in notes),
        table=table_html(table),
        plots="\n".join(_plot_html(Path(p)) for p in plots),
        groups="\n".join(
            f'<section class="group" id="group-{index}">{group.body}</section>' for index, group in enumerate(groups)
        ),
        css=_template("report.css"),
        js=_template("report.js"),
    )
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "index.html"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(path)
    return path


# ---------------------------------------------------------------- Table 1


def table_html(table: Table1) -> str:
    """Table 1 and its notes as HTML: the cells of the Table1 object, best values <strong>."""

    def cell(tag: str, c: Cell) -> str:
        return f"<{tag}><strong>{_esc(c.text)}</strong></{tag}>" if c.bold else f"<{tag}>{_esc(c.text)}</{tag}>"

    out = ["<table>", "<thead><tr>" + "".join(cell("th", Cell(h)) for h in table.head) + "</tr></thead><tbody>"]
    out += ["<tr>" + "".join(cell("td", c) for c in row) + "</tr>" for row in table.rows]
    out.append("</tbody></table>")
    out += [
        f"<p><strong>{_esc(n.label)}</strong> {_esc(n.text)}</p>" if n.label else f"<p>{_esc(n.text)}</p>"
        for n in table.notes
    ]
    return "\n".join(out)


def _esc(text: object) -> str:
    return html.escape(str(text), quote=True)


# ---------------------------------------------------------------- images


def display_rgb(linear: np.ndarray) -> np.ndarray:
    """uint8 (h, w, 3) of a linear HDR image as embedded: fitted into MAX_EMBED, tone-mapped, NaN/Inf magenta."""
    bad = ~np.all(np.isfinite(linear), axis=2)
    clean = np.where(np.isfinite(linear), np.maximum(linear, 0.0), 0.0).astype(np.float32)
    size = embed_size(linear.shape)
    small = _resize(clean, size)
    rgb = to_ldr(small)
    rgb[_resize(bad[..., None].astype(np.float32), size)[..., 0] > 0] = MAGENTA
    return rgb


def heat_rgb(output: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """uint8 (h, w, 3) heat map of mean_c (x - ref)^2 / (ref^2 + eps), log-scaled, NaN/Inf magenta.

    The error is computed at full resolution and box-averaged afterwards, so a downscaled heat map
    shows the mean error of each block rather than the error of blurred images.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        err = np.mean(
            (output.astype(np.float64) - reference) ** 2 / (reference.astype(np.float64) ** 2 + HEAT_EPS), axis=2
        )
    bad = ~np.isfinite(err)
    size = embed_size(output.shape)
    err = _resize(np.where(bad, 0.0, err).astype(np.float32)[..., None], size)[..., 0]
    lo, hi = HEAT_LOG10_RANGE
    with np.errstate(divide="ignore"):
        level = (np.clip(np.log10(err), lo, hi) - lo) / (hi - lo)
    rgb = _lut()[np.rint(level * 255).astype(np.int64)]
    rgb[_resize(bad[..., None].astype(np.float32), size)[..., 0] > 0] = MAGENTA
    return rgb


def embed_size(shape: tuple[int, ...]) -> tuple[int, int]:
    """(width, height) an image of this (H, W, ...) shape is embedded at: its own, or fitted into MAX_EMBED."""
    height, width = shape[0], shape[1]
    scale = min(1.0, MAX_EMBED[0] / width, MAX_EMBED[1] / height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def _resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Box-filter each channel of a float (H, W, C) image to (width, height) = size."""
    if (image.shape[1], image.shape[0]) == size:
        return image
    return np.stack(
        [
            np.asarray(Image.fromarray(np.ascontiguousarray(image[..., c])).resize(size, Image.Resampling.BOX))
            for c in range(image.shape[2])
        ],
        axis=2,
    )


def _lut() -> np.ndarray:
    return np.rint(colormaps[HEAT_COLORMAP](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)


def _png_uri(rgb: np.ndarray) -> str:
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buffer, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def _thumb_size(width: int, height: int) -> tuple[int, int]:
    """Fit into THUMB keeping the aspect, but never thinner than THUMB_MIN so a 4000x37 strip stays hoverable."""
    scale = min(THUMB[0] / width, THUMB[1] / height)
    return max(THUMB_MIN, round(width * scale)), max(THUMB_MIN, round(height * scale))


def _check(item: ReportImage) -> None:
    where = f"report image {item.scene_id!r} @ {item.spp} spp"
    ref = np.asarray(item.reference)
    if ref.ndim != 3 or ref.shape[2] != 3 or ref.shape[0] == 0 or ref.shape[1] == 0:
        raise ValueError(f"{where}: reference must be a non-empty (H, W, 3) array, got shape {ref.shape}")
    for name, out in item.outputs.items():
        if np.shape(out) != ref.shape:
            raise ValueError(f"{where}: output {name!r} has shape {np.shape(out)}, reference {ref.shape}")


def _figure(uri: str, caption: str, lines: list[str], size: tuple[int, int], *, warn: str = "") -> str:
    width, height = _thumb_size(*size)
    upscaled = " up" if width > size[0] or height > size[1] else ""
    extra = "".join(f"<div>{_esc(line)}</div>" for line in lines)
    if warn:
        extra += f'<div class="warn">{_esc(warn)}</div>'
    return (
        f'<figure class="fig"><figcaption>{_esc(caption)}</figcaption>'
        f'<div class="frame"><img class="px{upscaled}" src="{uri}" width="{width}" height="{height}" '
        f'alt="{_esc(caption)}"><div class="marker" hidden></div></div>'
        f'<canvas class="zoom" width="160" height="160" hidden></canvas>'
        f'<div class="metrics">{extra}</div></figure>'
    )


def report_group(item: ReportImage) -> ReportGroup:
    """One scene at one spp: images with their metrics, heat maps under them, the legend; NaN/Inf go to notes."""
    _check(item)
    notes = []
    reference = np.asarray(item.reference, dtype=np.float32)
    names = sorted(item.outputs, key=lambda n: n != "noisy")  # noisy first, then the given order
    size = embed_size(reference.shape)
    where = f"{item.scene_id} @ {item.spp} spp"
    images, heats = [], []
    for name in names:
        output = np.asarray(item.outputs[name], dtype=np.float32)
        bad = int(np.count_nonzero(~np.all(np.isfinite(output), axis=2)))
        warn = f"{bad} NaN/Inf pixels (magenta)" if bad else ""
        if bad:
            notes.append(f"{where}: {name} has {bad} NaN/Inf pixels, shown magenta.")
        lines = [f"{k} {_fmt(v)}" for k, v in item.metrics.get(name, {}).items()]
        images.append(_figure(_png_uri(display_rgb(output)), name, lines, size, warn=warn))
        heats.append(_figure(_png_uri(heat_rgb(output, reference)), f"error: {name}", [], size))
    ref_bad = int(np.count_nonzero(~np.all(np.isfinite(reference), axis=2)))
    if ref_bad:
        notes.append(f"{where}: the reference has {ref_bad} NaN/Inf pixels, shown magenta.")
    images.append(
        _figure(
            _png_uri(display_rgb(reference)),
            "reference",
            [],
            size,
            warn=f"{ref_bad} NaN/Inf pixels (magenta)" if ref_bad else "",
        )
    )
    height, width = reference.shape[:2]
    shown = (
        f"{width}x{height}"
        if size == (width, height)
        else f"{width}x{height}, embedded box-downscaled to {size[0]}x{size[1]}"
    )
    return ReportGroup(
        f"<h3>{_esc(item.scene_id)} &middot; {item.spp} spp <small>({shown})</small></h3>"
        f'<div class="row">{"".join(images)}</div>'
        f'<div class="row">{"".join(heats)}{_legend()}</div>',
        tuple(notes),
    )


def _legend() -> str:
    lo, hi = HEAT_LOG10_RANGE
    bar = _png_uri(_lut()[None, :, :])
    ticks = "".join(f"<span>1e{d}</span>" for d in range(int(lo), int(hi) + 1))
    return (
        f'<figure class="legend"><figcaption>relative squared error</figcaption>'
        f'<img class="bar" src="{bar}" width="240" height="14" alt="colour scale">'
        f'<div class="ticks">{ticks}</div>'
        f'<div class="metrics">mean<sub>c</sub> (x&minus;ref)&sup2; / (ref&sup2; + {HEAT_EPS:g}), log scale'
        f"<br>magenta: NaN/Inf</div></figure>"
    )


def _fmt(value: float) -> str:
    return f"{value:.4g}" if np.isfinite(value) else str(value)


def _plot_html(path: Path) -> str:
    if not path.is_file():
        raise ValueError(f"plot {path}: no such file")
    data = path.read_bytes()
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError(f"plot {path}: not a PNG file")
    uri = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
    return (
        f'<figure class="plot"><img src="{uri}" alt="{_esc(path.stem)}">'
        f"<figcaption>{_esc(path.stem)}</figcaption></figure>"
    )


_DISPLAY_RULES = (
    f"<li>Images: tone-mapped with clip(max(x, 0)<sup>1/{GAMMA}</sup>) to 8 bit, no exposure change "
    f"(the display mapping PSNR and SSIM are computed on).</li>"
    f"<li>Heat maps: per-pixel relative squared error mean<sub>c</sub> (x&minus;ref)&sup2; / "
    f"(ref&sup2; + {HEAT_EPS:g}), log<sub>10</sub> colour scale fixed from 1e{HEAT_LOG10_RANGE[0]:g} "
    f"to 1e{HEAT_LOG10_RANGE[1]:g} for every map.</li>"
    f"<li>NaN/Inf pixels are magenta. Images larger than {MAX_EMBED[0]}x{MAX_EMBED[1]} are box-downscaled "
    f"in linear space to fit before embedding; the zoom magnifies the embedded pixels.</li>"
    f"<li>Zoom: hover an image to magnify the same region in every image of its scene; click to pin or "
    f"unpin it. The magnification is set at the top.</li>"
)


def _template(name: str) -> str:
    """A file of the page template (templates/: the HTML skeleton, its CSS, the zoom's JavaScript)."""
    return resources.files("admc.pipeline.evaluation").joinpath("templates", name).read_text(encoding="utf-8")
