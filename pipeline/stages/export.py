"""`admc-pipe export`: a weights file's generators as ONNX graphs plus the JSON of what runs around them."""

from __future__ import annotations

from pathlib import Path

from admc.common.buffers import MISSING_LAYERS
from admc.errors import AdmcError
from admc.model.inference.denoiser import LOG_MAX, load_denoiser
from admc.model.inference.onnx_export import MANIFEST_NAME, export_generator, export_manifest
from admc.model.inference.fine_tuned_oidn import takes_clean_guides
from admc.model.transforms import transform_spec
from admc.stores.atomic import publishing, write_json


class ExportError(AdmcError, ValueError):
    """The export's output folder cannot be written as asked."""


def export_onnx(weights: Path, out_dir: Path) -> list[Path]:
    """Write `out_dir`/{branch}.onnx per branch and `out_dir`/admc.json; returns their paths. Weights that
    ship OIDN fine-tuned with them (train.oidn_minutes) also give `out_dir`/oidn-{branch}.tza: OIDN's own
    weight format, which any OIDN 2 filter takes as its "weights" (the blend's partner).

    Each file is published atomically, the JSON last, so a folder with an admc.json holds the graphs it
    names. Other files in `out_dir` are left alone."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"{out_dir}: exists and is not a folder (export writes a folder of graphs)")
    denoiser = load_denoiser(weights)  # checks the file: format, transforms, architecture
    generators = denoiser.generators
    written = [out_dir / f"{branch}.onnx" for branch in generators]
    partner = {branch: f"oidn-{branch}.tza" for branch in denoiser.oidn_partner or {}}
    try:
        for path, generator in zip(written, generators.values()):
            with publishing(path) as tmp:
                export_generator(generator, tmp)
        for branch, name in partner.items():
            with publishing(out_dir / name) as tmp:
                tmp.write_bytes(denoiser.oidn_partner[branch])
            written.append(out_dir / name)
        prefiltered = tuple(b for b in partner if takes_clean_guides(denoiser.oidn_partner[b]))
        manifest = export_manifest(
            generators, transform_spec(), LOG_MAX, MISSING_LAYERS, denoiser.oidn_blend, partner or None, prefiltered
        )
        write_json(out_dir / MANIFEST_NAME, {**manifest, "weights": Path(weights).name})
    except OSError as exc:
        raise ExportError(f"{out_dir}: cannot write the export there ({exc.strerror or exc})") from None
    return [*written, out_dir / MANIFEST_NAME]
