"""The test set on disk: the render stage's noisy EXRs, their references and sidecars, checked and read."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from admc.common.metrics import reference_floor, ssim_floor
from admc.pipeline.evaluation.baselines import noisy_color
from admc.pipeline.evaluation.records import EvalError, ReferenceFloors, TestImage
from admc.stores.exr import exr_layers, read_exr


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
        raise EvalError(
            f"{path}: sidecar is for scene {side['scene_id']!r} (reference={side['reference']}), "
            f"expected {scene_id!r} (reference={reference})"
        )
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
            images.append(
                TestImage(
                    folder.name,
                    int(side["spp"]),
                    path,
                    reference,
                    float(side["render_seconds"]),
                    int(ref_side.get("spp", 0)),
                    float(ref_side["render_seconds"]),
                )
            )
    return sorted(images, key=lambda t: (t.scene_id, t.spp))


def read_reference(path: Path) -> tuple[np.ndarray, ReferenceFloors]:
    """(diffuse + specular, its floors) of a reference EXR; the floors are NaN where the file has no
    variance layers (a reference rendered elsewhere)."""
    present = exr_layers(path)
    layers = read_exr(
        path, [name for name in ("diffuse", "specular", "diffuse_var", "specular_var") if name in present]
    )
    radiance = noisy_color(layers)
    variances = [layers[name] for name in ("diffuse_var", "specular_var") if name in layers]
    if not variances:
        return radiance, ReferenceFloors()
    variance = sum(variances)
    return radiance, ReferenceFloors(reference_floor(variance, radiance), ssim_floor(variance, radiance))


def by_scene(images: list[TestImage]) -> dict[str, list[TestImage]]:
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
