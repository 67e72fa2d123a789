"""Read the EXRs a user brings to `admc-pipe denoise` and write the denoised result.

Three layouts are accepted:

* one EXR as a renderer wrote it, recognised by its channel names (`denoise_formats`): Blender Cycles
  multilayer files, pbrt-v4 gbuffer films, Mitsuba `aov` outputs, or any file with a `--layers` map;
  its normals are brought into camera space or the file is refused (`denoise_layers`). A Blender file
  gets its result back in Blender's layout (`VL.Combined.R/G/B/A`), which its compositor reads;

* one multi-layer EXR with admc's layer names: `diffuse.R/G/B`, `albedo.R/G/B`, `normal.X/Y/Z`,
  optional `specular.R/G/B`, `depth.Z`, `coverage.A`, `diffuse_var.R/G/B`, `specular_var.R/G/B` (what
  `admc-pipe render` writes; weights with model.noise_input need the variance layers);
* Open Image Denoise style separate files sharing a base name: the colour `NAME.hdr.exr` (or
  `NAME.exr`), `NAME.alb.exr`, `NAME.nrm.exr`, optional `NAME.diffuse.exr` + `NAME.specular.exr`
  (then they are the split and the colour is not needed) and optional `NAME.depth.exr`. A combined
  colour alone cannot be split, so it is denoised as diffuse only (demodulated by albedo; a mirror
  or glass reflection is then treated as texture-free light, which the diffuse network was not
  trained on: expect it blurrier than with a proper split).

Missing depth becomes the constant depth feature 1.0 (the value of environment pixels, so no false
geometry edges) with coverage 1: the denoiser fills them (MISSING_LAYERS), this module says so.
NaN/Inf pixels are not errors: they are counted here and repaired by the denoiser, which reports what
it did. Everything else that is wrong raises DenoiseInputError (or ExrError from the reader) naming
the file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from admc.common.buffers import BEAUTY, DENOISER_LAYERS, MISSING_LAYERS, VARIANCE_LAYERS
from admc.errors import AdmcError
from admc.stores.exr import exr_layers, nonfinite_report, read_exr, read_image, write_exr
from admc.stores.exr_parts import channel_names, read_channels, write_channels

from .denoise_formats import LayerMap, Recognised, recognise
from .denoise_layers import build_layers, camera_normals, missing_roles

if TYPE_CHECKING:  # reading and checking the input needs no torch, so a bad file is named in a second
    from admc.model.inference.result import DenoiseResult

SUFFIXES = {
    "colour": ".hdr.exr",
    "albedo": ".alb.exr",
    "normal": ".nrm.exr",
    "diffuse": ".diffuse.exr",
    "specular": ".specular.exr",
    "depth": ".depth.exr",
}
"""File name endings of the separate-file layout (the first three are Open Image Denoise's)."""


class DenoiseInputError(AdmcError, ValueError):
    """The files given to `denoise` do not form one complete, consistent input."""


@dataclass
class DenoiseInput:
    """Layers ready for FullImageDenoiser, where each came from, and what was assumed."""

    layers: dict[str, np.ndarray]  # diffuse, [specular], albedo, normal, [depth], [coverage]
    sources: dict[str, Path]  # layer -> the file it was read from
    notes: list[str] = field(default_factory=list)
    blender_layer: str | None = None  # a Blender file's view layer: the output keeps its layout
    alpha: np.ndarray | None = None  # and its Combined alpha
    attributes: dict = field(default_factory=dict)

    @property
    def paths(self) -> set[Path]:
        return {p.resolve() for p in self.sources.values()}

    @property
    def nonfinite(self) -> dict[str, dict[str, int]]:
        """NaN/Inf (and invalid negative) counts per layer as read, before the denoiser repairs them."""
        return nonfinite_report(self.layers)


def load_denoise_input(path: Path, mapping: LayerMap | None = None) -> DenoiseInput:
    """Read one EXR (admc's layers, a renderer's, or a `mapping`'s), or the separate files of NAME (given as
    NAME.hdr.exr, NAME.exr or NAME)."""
    path, mapping = Path(path), mapping or LayerMap()
    if path.is_file() and not path.name.endswith(SUFFIXES["colour"]):
        header, names = channel_names(path)  # raises ExrError naming the file if it is no EXR or is corrupt
        found = recognise(path, header, names, mapping)
        if found is not None and found.format == "admc":
            return _load_multilayer(path, exr_layers(path))
        if found is not None and (found.format != "EXR" or not _sibling(_base(path), "albedo").exists()):
            return _load_renderer(path, found, names)
        if found is None and not _sibling(_base(path), "albedo").exists():
            return _load_multilayer(path, exr_layers(path))
    return _load_separate(_base(path), given=path, mapping=mapping)


def _load_renderer(path: Path, found: Recognised, names: list[str]) -> DenoiseInput:
    """A renderer's EXR: its layers as admc's, its normals in camera space (or a refusal naming the file)."""
    missing = missing_roles(found)
    if missing:
        layers = sorted({name.rpartition(".")[0] or "R,G,B" for name in names})
        hint = (
            "; in Blender switch on View Layer Properties > Passes > Data > Denoising Data (Cycles)"
            if found.format.startswith("Blender")
            else "; name them with --layers ROLE=LAYER"
        )
        raise DenoiseInputError(
            f"{path}: read as {found.format}, lacks {', '.join(missing)} needed to denoise "
            f"(it holds {', '.join(layers)}){hint}"
        )
    wanted = {n for role in found.channels.values() for n in role}
    wanted |= {n for role in found.light_passes.values() for n in role}
    if found.blender_layer is not None:
        wanted.add(f"{found.blender_layer}.Combined.A" if found.blender_layer else "Combined.A")
    header, planes = read_channels(path, wanted)
    layers, notes = build_layers(path, found, planes)
    alpha_name = f"{found.blender_layer}.Combined.A" if found.blender_layer else "Combined.A"
    result = DenoiseInput(
        layers,
        {name: path for name in layers},
        notes,
        blender_layer=found.blender_layer,
        alpha=planes.get(alpha_name),
        attributes=found.attributes,
    )
    if "specular" not in layers and found.light_passes:
        result.notes.append(f"{path.name}: no specular layer, only the diffuse network runs")
    _note_missing_depth(result, path.name)
    return result


def _base(path: Path) -> Path:
    """NAME from NAME.hdr.exr, NAME.alb.exr (any ending of SUFFIXES), NAME.exr or NAME itself."""
    for ending in (*SUFFIXES.values(), ".exr"):
        if path.name.endswith(ending):
            return path.with_name(path.name[: -len(ending)])
    return path


def _sibling(base: Path, role: str) -> Path:
    return base.with_name(base.name + SUFFIXES[role])


def _load_multilayer(path: Path, present: list[str]) -> DenoiseInput:
    missing = [name for name in ("diffuse", "albedo", "normal") if name not in present]
    if missing:
        raise DenoiseInputError(
            f"{path}: lacks layer(s) {', '.join(missing)} needed to denoise (it holds "
            f"{', '.join(present) or 'no admc layers'}); expected diffuse.R/G/B, "
            f"albedo.R/G/B, normal.X/Y/Z and optionally specular, depth.Z, coverage.A (or, as "
            f"separate files, {path.stem}.alb.exr and {path.stem}.nrm.exr beside it)"
        )
    wanted = [name for name in (*DENOISER_LAYERS, *VARIANCE_LAYERS) if name in present]
    layers = read_exr(path, wanted)
    notes = []
    if "specular" not in layers:
        notes.append(f"{path.name}: no specular layer, only the diffuse network runs")
    result = DenoiseInput(layers, {name: path for name in layers}, notes)
    _note_missing_depth(result, path.name)
    return result


def _load_separate(base: Path, given: Path, mapping: LayerMap) -> DenoiseInput:
    files = {role: _sibling(base, role) for role in SUFFIXES}
    plain = base.with_name(base.name + ".exr")
    if plain.is_file() and (given == plain or not files["colour"].exists()):
        files["colour"] = plain
    split = files["diffuse"].exists() or files["specular"].exists()
    if split and not (files["diffuse"].exists() and files["specular"].exists()):
        have, lack = ("diffuse", "specular") if files["diffuse"].exists() else ("specular", "diffuse")
        raise DenoiseInputError(f"{files[have]}: found without {files[lack]}; give both parts of the split or neither")
    if not split and not files["colour"].exists():
        raise DenoiseInputError(
            f"{given}: no such file, and no colour file {files['colour'].name} or {base.name}.exr beside it"
        )
    for role in ("albedo", "normal"):
        if not files[role].exists():
            raise DenoiseInputError(
                f"{files[role]}: missing; the {role} file is required beside "
                f"{(files['diffuse'] if split else files['colour']).name}"
            )

    roles = ["diffuse", "specular"] if split else ["colour"]
    roles += ["albedo", "normal"] + (["depth"] if files["depth"].exists() else [])
    layers, sources = {}, {}
    for role in roles:
        name = "diffuse" if role == "colour" else role
        layers[name] = _read_plain(files[role], channels=1 if role == "depth" else 3)
        sources[name] = files[role]
    _check_sizes(layers, sources)
    found = Recognised(
        "OIDN files", {"normal": ("R", "G", "B")}, normal_space=mapping.normal_space, camera_frame=mapping.camera_frame
    )
    if mapping.world_to_camera is not None:
        found.world_to_camera, found.camera_source = np.asarray(mapping.world_to_camera, np.float64), "given"
        found.normal_space = "world" if mapping.normal_space == "auto" else mapping.normal_space
    layers["normal"], space_note = camera_normals(files["normal"], found, layers["normal"])
    if not split:
        notes = [
            f"{files['colour'].name}: one combined colour and no {base.name}.diffuse.exr/.specular.exr "
            f"split, denoised as diffuse only"
        ]
    elif files["colour"].exists():
        notes = [f"{files['colour'].name}: not read, the diffuse/specular split is used"]
    else:
        notes = []
    result = DenoiseInput(layers, sources, notes + [space_note])
    _note_missing_depth(result, base.name)
    return result


def _read_plain(path: Path, channels: int) -> np.ndarray:
    """First `channels` channels of a plain EXR (R,G,B[,A] or X,Y,Z); one channel is spread to three."""
    exr_layers(path)  # refuses files that are not EXR (read_image would read a PNG happily)
    image = read_image(path)
    if image.shape[2] == 1 and channels == 3:
        image = np.repeat(image, 3, axis=2)
    if image.shape[2] < channels:
        raise DenoiseInputError(f"{path}: has {image.shape[2]} channel(s), needs {channels}")
    return np.ascontiguousarray(image[:, :, :channels])


def _check_sizes(layers: dict[str, np.ndarray], sources: dict[str, Path]) -> None:
    sizes = {name: a.shape[:2] for name, a in layers.items()}
    if len(set(sizes.values())) > 1:
        listing = ", ".join(f"{sources[n].name} {h}x{w}" for n, (h, w) in sizes.items())
        raise DenoiseInputError(f"{sources['diffuse'].parent}: the input files differ in size ({listing}, as HxW)")


def _note_missing_depth(result: DenoiseInput, where: str) -> None:
    """Tell the user that the denoiser will fill an absent depth (and coverage) with MISSING_LAYERS' values."""
    if "depth" not in result.layers:
        result.notes.append(
            f"{where}: no depth, using the constant depth feature {MISSING_LAYERS['depth']} "
            f"(as for environment pixels) and coverage {MISSING_LAYERS['coverage']}"
        )


def output_paths(inputs: list[Path], output: Path | None = None) -> list[Path]:
    """Where each input's result goes: `output` for a single input, else INPUT.denoised.exr beside it
    (NAME.denoised.exr for NAME.hdr.exr). Refuses, before any work, a batch in which two inputs would
    write the same file or an output would replace an input of the batch."""
    targets = (
        [Path(output)]
        if output is not None
        else [path.with_name(path.name.removesuffix(".exr").removesuffix(".hdr") + ".denoised.exr") for path in inputs]
    )
    first: dict[Path, Path] = {}
    given = {path.resolve(): path for path in inputs}
    for path, target in zip(inputs, targets):
        key = target.resolve()
        if key in first:
            raise DenoiseInputError(
                f"{first[key]} and {path} would both be written to {target}; denoise them in "
                "separate runs, each with its own --output"
            )
        if key in given:
            raise DenoiseInputError(
                f"{target}: the output for {path} is also an input of this batch; denoise "
                "them in separate runs, or give --output for one input"
            )
        first[key] = path
    return targets


def check_output_path(path: Path, source: DenoiseInput) -> None:
    """Refuse an output that is not an .exr or would overwrite an input, before any work is spent."""
    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise DenoiseInputError(f"{path}: the output must be an .exr file")
    if path.is_dir():
        raise DenoiseInputError(f"{path}: is a directory; the output names the .exr file to write")
    if path.resolve() in source.paths:
        raise DenoiseInputError(f"{path}: is one of the input files; choose another output name")


def write_denoised(path: Path, result: DenoiseResult, *, source: DenoiseInput, layers: bool = True) -> None:
    """EXR (float32) with the final image as plain R, G, B and, if `layers`, the `diffuse.*` and
    `specular.*` parts; written atomically. Refuses to overwrite any file of `source`."""
    path = Path(path)
    check_output_path(path, source)
    if source.blender_layer is not None:
        _write_blender(path, result, source, layers)
        return
    planes = {BEAUTY: result.image}
    if layers:
        planes.update(
            {
                name: part
                for name, part in (("diffuse", result.diffuse), ("specular", result.specular))
                if part is not None
            }
        )
    write_exr(path, planes, precision="float", attributes={"admc_branches": ",".join(result.branches)})


BLENDER_PASS_NAMES = {"diffuse": "admc Diffuse", "specular": "admc Specular"}
"""The passes a Blender input's result carries beside Combined (Blender's compositor lists them by these names)."""


def _write_blender(path: Path, result: DenoiseResult, source: DenoiseInput, layers: bool) -> None:
    """Blender's multilayer layout: the denoised image as the view layer's Combined (RGBA, the input's
    alpha), and the denoised branches as passes of that view layer."""
    prefix = f"{source.blender_layer}." if source.blender_layer else ""
    alpha = source.alpha if source.alpha is not None else np.ones(result.image.shape[:2], np.float32)
    channels = {f"{prefix}Combined.{c}": result.image[:, :, i] for i, c in enumerate("RGB")}
    channels[f"{prefix}Combined.A"] = alpha
    if layers:
        for name, part in (("diffuse", result.diffuse), ("specular", result.specular)):
            if part is not None:
                channels.update({f"{prefix}{BLENDER_PASS_NAMES[name]}.{c}": part[:, :, i] for i, c in enumerate("RGB")})
    attributes = {"admc_branches": ",".join(result.branches), **source.attributes}
    attributes.setdefault("BlenderMultiChannel", "Blender V2.55.1 and newer")
    write_channels(path, channels, attributes=attributes)
