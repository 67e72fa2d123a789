"""Which renderer wrote an EXR, told by its channel names, and where admc's layers are in it.

Recognised (each by the names that program writes):

* Blender (Cycles) multilayer EXRs, any view-layer name `VL`: `VL.Combined.R/G/B[/A]`,
  `VL.Denoising Albedo.R/G/B`, `VL.Denoising Normal.X/Y/Z` (else `VL.Normal`), `VL.Denoising Depth.Z`,
  and the light passes when present, under Blender 5's names (`Diffuse Direct`, `Diffuse Indirect`,
  `Diffuse Color`, `Glossy ...`) or the short ones of earlier versions (`DiffDir`, `DiffInd`,
  `DiffCol`, ...): then diffuse = (direct + indirect) x colour and specular = Combined - diffuse.
  Blender 5 writes each pass as a part of its own; every part is read.
* pbrt-v4 `gbuffer` films: `R,G,B`, `Albedo.R/G/B`, `Ns.X/Y/Z` (`Nsx/Nsy/Nsz` before 2021), `P.X/Y/Z`,
  `Variance.R/G/B`, with the `worldToCamera` header attribute pbrt writes.
* Mitsuba 3's `aov` integrator: the film's `R,G,B`, an `albedo` AOV, a shading-normal AOV named as in
  Mitsuba's documentation or after its type (`nn`, `sh_normal`, `normal`), a depth AOV (`dd.y`, `depth`;
  channel `T`). The AOV types are not in the file, so other names need `--layers`.
* admc's own layers (`diffuse.R`, `normal.X`, ...: what `admc-pipe render` writes).
* Anything else through a `LayerMap` (`--layers` on the command line, or a small TOML file).

The normals' frame travels with the result (`Recognised.normal_space`); `denoise_normals` turns them
into admc's camera frame or refuses.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from admc.common.buffers import LAYERS
from admc.errors import AdmcError

ROLES = ("colour", "diffuse", "specular", "albedo", "normal", "depth", "diffuse_var", "specular_var")
"""What a layer of the user's file can stand for: `colour` is a combined image (denoised as diffuse
only), the others are admc's layers of the same name."""
RGB_NAMES = (("R", "G", "B"), ("r", "g", "b"))
XYZ_NAMES = (("X", "Y", "Z"), ("x", "y", "z"), ("R", "G", "B"))
NORMAL_SPACES = ("auto", "camera", "world")
CAMERA_FRAMES = ("admc", "blender", "cycles", "pbrt", "mitsuba")

# Blender's pass names: Blender 5's, then the short ones multilayer EXRs of Blender 2.8-4.x carry.
BLENDER_PASSES = {
    "diffuse_direct": ("Diffuse Direct", "DiffDir"),
    "diffuse_indirect": ("Diffuse Indirect", "DiffInd"),
    "diffuse_colour": ("Diffuse Color", "DiffCol"),
    "albedo": ("Denoising Albedo",),
    "normal": ("Denoising Normal",),
    "world_normal": ("Normal",),
    "depth": ("Denoising Depth", "Depth"),
    "environment": ("Environment", "Env"),
}
MITSUBA_NORMALS = ("nn", "sh_normal", "normal", "normals", "sh_normals", "shading_normal")
MITSUBA_DEPTHS = ("dd.y", "dd", "depth")


class LayerMapError(AdmcError, ValueError):
    """A --layers mapping names an unknown role, a layer the file lacks, or a bad value."""


@dataclass
class LayerMap:
    """The user's own mapping: role -> layer name (its channels in R,G,B / X,Y,Z order) or an explicit
    list of full channel names, plus how the normals were written."""

    roles: dict[str, tuple[str, ...]] = field(default_factory=dict)
    normal_space: str = "auto"
    world_to_camera: tuple[float, ...] | None = None
    camera_frame: str = "admc"
    source: str = "--layers"

    @classmethod
    def parse(cls, items: list[str] | None, normal_space: str = "auto", world_to_camera: str | None = None) -> LayerMap:
        """From `--layers` values (each `ROLE=LAYER`, `ROLE=CH1,CH2,CH3`, or a .toml file's path) and the
        `--normal-space` / `--world-to-camera` options (which win over the file's keys)."""
        mapping = cls()
        for item in items or []:
            if item.endswith(".toml") and "=" not in item:
                mapping._merge_toml(Path(item))
            elif "=" in item:
                role, _, value = item.partition("=")
                mapping._set(role.strip(), value.strip(), "--layers")
            else:
                raise LayerMapError(
                    f"--layers {item!r}: expected ROLE=LAYER (roles: {', '.join(ROLES)}) or a .toml file"
                )
        if normal_space != "auto":
            mapping._set("normal_space", normal_space, "--normal-space")
        if world_to_camera:
            mapping._set("world_to_camera", world_to_camera, "--world-to-camera")
        return mapping

    def _merge_toml(self, path: Path) -> None:
        if not path.is_file():
            raise LayerMapError(f"{path}: no such layers file")
        try:
            data = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise LayerMapError(f"{path}: not valid TOML ({exc})") from None
        self.source = str(path)
        for key, value in data.items():
            if key == "layers" and isinstance(value, dict):
                for role, names in value.items():
                    self._set(role, names, f"{path} [layers]")
            else:
                self._set(key, value, str(path))

    def _set(self, key: str, value, where: str) -> None:
        if key == "normal_space":
            if value not in NORMAL_SPACES:
                raise LayerMapError(f"{where}: normal_space must be one of {', '.join(NORMAL_SPACES)}, got {value!r}")
            self.normal_space = value
        elif key == "camera_frame":
            if value not in CAMERA_FRAMES:
                raise LayerMapError(f"{where}: camera_frame must be one of {', '.join(CAMERA_FRAMES)}, got {value!r}")
            self.camera_frame = value
        elif key == "world_to_camera":
            numbers = value.replace(",", " ").split() if isinstance(value, str) else np.ravel(value).tolist()
            try:
                matrix = tuple(float(v) for v in numbers)
            except (TypeError, ValueError):
                matrix = ()
            if len(matrix) not in (9, 16) or not np.isfinite(matrix).all():
                raise LayerMapError(
                    f"{where}: world_to_camera must be 16 (4x4, row by row) or 9 numbers, got {value!r}"
                )
            self.world_to_camera = matrix
        elif key in ROLES:
            names = tuple(n.strip() for n in value.split(",")) if isinstance(value, str) else tuple(value)
            if not names or not all(isinstance(n, str) and n for n in names):
                raise LayerMapError(f"{where}: {key} must name a layer or its channels, got {value!r}")
            self.roles[key] = names
        else:
            raise LayerMapError(
                f"{where}: unknown key {key!r}; the roles are {', '.join(ROLES)}, and normal_space, "
                "world_to_camera, camera_frame"
            )

    @property
    def declares(self) -> bool:
        return bool(self.roles) or self.normal_space != "auto" or self.world_to_camera is not None


@dataclass
class Recognised:
    """Where each admc layer is in a file: role -> full channel names, how to combine Blender's light
    passes, and what is known about the normals' frame."""

    format: str
    channels: dict[str, tuple[str, ...]]
    normal_space: str  # "camera" (in camera_frame), "world", or "auto" (unknown)
    camera_frame: str = "admc"
    world_to_camera: np.ndarray | None = None
    camera_source: str = "file"  # where world_to_camera came from: "file" or "given"
    blender_layer: str | None = None  # the view layer of a Blender file (its output keeps it)
    light_passes: dict[str, tuple[str, ...]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    attributes: dict = field(default_factory=dict)


def group(names: list[str]) -> dict[str, list[str]]:
    """Full channel names by layer: 'VL.Denoising Albedo.R' -> {'VL.Denoising Albedo': ['R']}."""
    layers: dict[str, list[str]] = {}
    for full in names:
        layer, _, channel = full.rpartition(".")
        layers.setdefault(layer, []).append(channel)
    return layers


def layer_channels(layers: dict[str, list[str]], layer: str, count: int) -> tuple[str, ...] | None:
    """The full names of `layer`'s first `count` channels in R,G,B or X,Y,Z order; None if it lacks them."""
    have = layers.get(layer)
    if have is None:
        return None
    prefix = f"{layer}." if layer else ""
    if count == 1:
        return (
            (prefix + have[0],)
            if len(have) == 1
            else next(((prefix + c,) for c in ("Z", "Y", "T", "V", "R") if c in have), None)
        )
    for order in (*RGB_NAMES, *XYZ_NAMES):
        if all(c in have for c in order[:count]):
            return tuple(prefix + c for c in order[:count])
    return None


def recognise(path: Path, header: dict, names: list[str], mapping: LayerMap) -> Recognised | None:
    """The format of a single EXR with these channels, or None (then it may be an OIDN file set)."""
    layers = group(names)
    found = (
        _admc(layers) or _blender(layers, header) or _pbrt(layers, header) or _mitsuba(layers, header) or _plain(layers)
    )
    if mapping.roles:
        found = _apply_mapping(path, layers, names, mapping, found)
    if found is not None:
        _declare_space(found, mapping)
    return found


def _admc(layers) -> Recognised | None:
    if "diffuse" not in layers:
        return None
    channels = {
        name: tuple(f"{name}.{c}" for c in LAYERS[name].channels)
        for name in ("diffuse", "specular", "albedo", "normal", "depth", "coverage", "diffuse_var", "specular_var")
        if name in layers and all(c in layers[name] for c in LAYERS[name].channels)
    }
    return Recognised("admc", channels, normal_space="camera")


def _blender(layers, header) -> Recognised | None:
    combined = [layer for layer in layers if layer.endswith(".Combined") or layer == "Combined"]
    if not combined:
        return None
    view_layer = combined[0].removesuffix("Combined").removesuffix(".")
    prefix = f"{view_layer}." if view_layer else ""

    def find(role: str, count: int) -> tuple[str, ...] | None:
        return next((c for name in BLENDER_PASSES[role] if (c := layer_channels(layers, prefix + name, count))), None)

    # Cycles writes its Denoising Normal in its camera space (z forward), the Normal pass in world space.
    camera_normal = find("normal", 3)
    channels = {
        "colour": layer_channels(layers, prefix + "Combined", 3),
        "albedo": find("albedo", 3),
        "normal": camera_normal or find("world_normal", 3),
        "depth": find("depth", 1),
        "environment": find("environment", 3),
    }
    channels = {role: names for role, names in channels.items() if names}
    light = {role: find(role, 3) for role in ("diffuse_direct", "diffuse_indirect", "diffuse_colour")}
    found = Recognised(
        "Blender",
        channels,
        normal_space="camera" if camera_normal else "world",
        camera_frame="cycles" if camera_normal else "blender",
        blender_layer=view_layer,
        attributes={k: v for k, v in header.items() if k == "BlenderMultiChannel"},
    )
    if all(light.values()):
        found.light_passes = light
    else:
        found.notes.append(
            f"no diffuse light passes (Diffuse Direct, Diffuse Indirect, Diffuse Color) in view layer "
            f"{view_layer or '(none)'}: Combined is denoised as diffuse only; switch them on in "
            "Blender's View Layer Properties > Passes > Light for the diffuse/specular split"
        )
    return found


def _pbrt(layers, header) -> Recognised | None:
    if "Albedo" not in layers or "" not in layers:
        return None
    normal = layer_channels(layers, "Ns", 3) or (
        ("Nsx", "Nsy", "Nsz") if {"Nsx", "Nsy", "Nsz"} <= set(layers[""]) else None
    )
    position = layer_channels(layers, "P", 3) or (("Px", "Py", "Pz") if {"Px", "Py", "Pz"} <= set(layers[""]) else None)
    channels = {
        "colour": layer_channels(layers, "", 3),
        "albedo": layer_channels(layers, "Albedo", 3),
        "normal": normal,
        "position": position,
    }
    spp = header.get("samplesPerPixel")
    if "Variance" in layers and spp:
        channels["diffuse_var"] = layer_channels(layers, "Variance", 3)
    found = Recognised(
        "pbrt-v4 gbuffer", {k: v for k, v in channels.items() if v}, normal_space="auto", camera_frame="pbrt"
    )
    if "worldToCamera" in header:
        found.world_to_camera = np.asarray(header["worldToCamera"], np.float64).reshape(4, 4)
    if spp:
        found.attributes["samplesPerPixel"] = int(spp)
    return found


def _mitsuba(layers, header) -> Recognised | None:
    if not str(header.get("generatedBy", "")).startswith("Mitsuba"):
        return None
    channels = {
        "colour": layer_channels(layers, "", 3),
        "albedo": layer_channels(layers, "albedo", 3),
        "normal": next((c for name in MITSUBA_NORMALS if (c := layer_channels(layers, name, 3))), None),
        "depth": next((c for name in MITSUBA_DEPTHS if (c := layer_channels(layers, name, 1))), None),
    }
    return Recognised(
        "Mitsuba aov", {k: v for k, v in channels.items() if v}, normal_space="world", camera_frame="mitsuba"
    )


def _plain(layers) -> Recognised | None:
    """A file of another program: only its beauty (R,G,B) is known until --layers names the rest."""
    colour = layer_channels(layers, "", 3)
    return Recognised("EXR", {"colour": colour}, normal_space="auto") if colour else None


def _apply_mapping(path: Path, layers, names: list[str], mapping: LayerMap, found: Recognised | None) -> Recognised:
    found = found or Recognised("EXR", {}, normal_space="auto")
    found.format += f" with {mapping.source}"
    for role, given in mapping.roles.items():
        count = 1 if role == "depth" else 3
        if len(given) == count and all(n in names for n in given):
            found.channels[role] = given
            continue
        channels = layer_channels(layers, given[0], count) if len(given) == 1 else None
        if channels is None:
            raise LayerMapError(
                f"{path}: {mapping.source} maps {role} to {','.join(given)}, which the file does not "
                f"hold as {count} channel(s); its layers are {', '.join(sorted(layers)) or '(none)'}"
            )
        found.channels[role] = channels
    if {"diffuse", "specular"} & set(mapping.roles):
        found.light_passes = {}
    return found


def _declare_space(found: Recognised, mapping: LayerMap) -> None:
    """The user's declarations win over what the format implies."""
    if mapping.normal_space != "auto":
        found.normal_space = mapping.normal_space
    if mapping.world_to_camera is not None:
        found.world_to_camera = np.asarray(mapping.world_to_camera, np.float64)
        found.camera_source = "given"
        if mapping.normal_space == "auto" and found.normal_space == "auto":
            found.normal_space = "world"
    if mapping.camera_frame != "admc" or found.format.startswith("EXR"):
        found.camera_frame = mapping.camera_frame
