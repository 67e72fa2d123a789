"""From a recognised renderer EXR to admc's layers: the diffuse/specular split from light passes,
depth and coverage from what the renderer wrote, and normals in admc's camera frame (or a refusal).

admc's networks read camera-space normals; a world-space normal taken for one is a silently worse
result, so a file whose normals are in world space is rotated with the camera matrix it carries (pbrt-v4's
`worldToCamera`) or that the user gives (`--world-to-camera`), and refused without one. Where the frame is
unknown (OIDN file sets, files mapped with `--layers`), it is detected: camera-space normals of what a
camera sees face it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from admc.common.camera import facing_share, to_admc_camera, world_to_admc_camera
from admc.errors import AdmcError
from admc.pipeline.render.blender.passes import coverage

from .denoise_formats import Recognised

FACING_MIN = 0.9
"""Camera-space normals face the camera on at least this share of the pixels that have one (grazing
angles at the borders and bump-mapped normals make up the rest); world-space ones, on a wall, floor and
ceiling alike, do not."""
PERSPECTIVE_FIT_MIN = 0.8
"""A position buffer is in a camera's frame when this share of its pixels lies on their pixel's ray."""
PERSPECTIVE_TOLERANCE = 0.5
"""... within this many pixels."""
NO_HIT_DEPTH = 1e9
"""Blender's Depth pass holds 1e10 where the camera ray hit nothing."""

CAMERA_HINTS = {
    "Blender": "in Blender's Python console: print(*[v for r in C.scene.camera.matrix_world.inverted() for v in r])",
    "Mitsuba aov": "the inverse of the sensor's to_world: print(*sensor.world_transform().inverse().matrix.numpy()"
    ".ravel())",
}


class NormalSpaceError(AdmcError, ValueError):
    """The normals are in world space (or look so) and no camera to rotate them into is known."""


def missing_roles(found: Recognised) -> list[str]:
    """The layers a denoiser cannot do without that this file lacks."""
    missing = [] if found.channels.get("colour") or found.channels.get("diffuse") else ["colour (or diffuse)"]
    return missing + [role for role in ("albedo", "normal") if role not in found.channels]


def build_layers(
    path: Path, found: Recognised, planes: dict[str, np.ndarray]
) -> tuple[dict[str, np.ndarray], list[str]]:
    """admc's layers (diffuse, [specular], albedo, normal, [depth, coverage], [variances]) and notes."""

    def stack(role: str) -> np.ndarray:
        return np.stack([planes[name] for name in found.channels[role]], axis=-1).astype(np.float32)

    notes = [f"{path.name}: read as {found.format}", *(f"{path.name}: {n}" for n in found.notes)]
    layers: dict[str, np.ndarray] = {}
    if found.light_passes:
        direct, indirect, colour = (
            np.stack([planes[n] for n in found.light_passes[k]], axis=-1)
            for k in ("diffuse_direct", "diffuse_indirect", "diffuse_colour")
        )
        layers["diffuse"] = ((direct + indirect) * colour).astype(np.float32)
        layers["specular"] = np.maximum(stack("colour") - layers["diffuse"], 0.0).astype(np.float32)
    elif "diffuse" in found.channels:
        layers["diffuse"] = stack("diffuse")
        if "specular" in found.channels:
            layers["specular"] = stack("specular")
    else:
        layers["diffuse"] = stack("colour")
        if found.format != "admc":
            notes.append(f"{path.name}: one combined colour and no diffuse/specular split, denoised as diffuse only")
    layers["albedo"] = stack("albedo")
    for role in ("coverage", "diffuse_var", "specular_var"):
        if role in found.channels:
            layers[role] = stack(role)
    if "diffuse_var" in layers and "samplesPerPixel" in found.attributes:  # pbrt: a sample variance
        layers["diffuse_var"] = layers["diffuse_var"] / np.float32(found.attributes["samplesPerPixel"])
    normal = stack("normal")
    if "position" in found.channels:
        layers["depth"], layers["coverage"], space_note = _from_positions(path, found, stack("position"), normal)
        notes.append(space_note)
    elif "depth" in found.channels:
        depth = stack("depth")
        hit = np.isfinite(depth) & (depth > 0) & (depth < NO_HIT_DEPTH)
        layers["depth"] = np.where(hit, depth, 0.0).astype(np.float32)
        if "coverage" in layers:
            pass
        elif "environment" in found.channels and "colour" in found.channels:  # Blender: see passes.coverage
            layers["coverage"] = coverage(layers["depth"], stack("colour"), stack("environment"))
        else:
            layers["coverage"] = hit.astype(np.float32)
    layers["normal"], space_note = camera_normals(path, found, normal)
    notes.append(space_note)
    return layers, [n for n in notes if n]


def camera_normals(path: Path, found: Recognised, normal: np.ndarray) -> tuple[np.ndarray, str]:
    """Normals in admc's camera frame, and a note on what was done; refuses where that cannot be known."""
    where = ", ".join(found.channels["normal"])
    if found.normal_space == "camera":
        note = f"{path.name}: normals ({where}) taken as {found.camera_frame} camera space"
        return to_admc_camera(normal, found.camera_frame), "" if found.format == "admc" else note
    if found.normal_space == "world":
        if found.world_to_camera is None:
            hint = CAMERA_HINTS.get(found.format, "the inverse of the camera's to-world matrix")
            raise NormalSpaceError(
                f"{path}: the normals ({where}) are in world space and the file carries no camera to turn them into "
                f"camera space, which admc reads; give the world-to-camera matrix with --world-to-camera "
                f"'16 numbers, row by row' ({hint}), or --normal-space camera if they are camera-space already"
            )
        return world_to_admc_camera(normal, found.world_to_camera, found.camera_frame), (
            f"{path.name}: world-space normals ({where}) rotated into camera space with the "
            f"{'given' if found.camera_source == 'given' else 'file' + chr(39) + 's'} world-to-camera matrix"
        )
    share, count = facing_share(to_admc_camera(normal, found.camera_frame))
    if share >= FACING_MIN:
        return to_admc_camera(normal, found.camera_frame), (
            f"{path.name}: normals ({where}) taken as camera space: {share:.0%} of the {count} pixels with a normal "
            f"face the camera (--normal-space world --world-to-camera ... if they are world-space)"
        )
    raise NormalSpaceError(
        f"{path}: the normals ({where}) face away from the camera on {1 - share:.0%} of the {count} pixels with one: "
        f"they look like world-space normals, and admc reads camera-space ones; give the camera with "
        f"--normal-space world --world-to-camera '16 numbers, row by row', or --normal-space camera to take them as "
        f"they are"
    )


def _from_positions(path: Path, found: Recognised, position: np.ndarray, normal: np.ndarray):
    """pbrt-v4: depth (distance to the camera), coverage (a surface was seen) and the frame of P and the
    normals, which the film writes in camera space by default and in world space with
    `coordinatesystem "world"`; the positions tell which."""
    hit = np.linalg.norm(normal, axis=-1, keepdims=True) > 0
    candidates = {"camera": position}
    if found.world_to_camera is not None:
        m = np.asarray(found.world_to_camera, np.float64).reshape(4, 4)
        candidates["world"] = (position.astype(np.float64) @ m[:3, :3].T + m[:3, 3]).astype(np.float32)
    if found.normal_space == "auto":
        fits = {space: _perspective_fit(p, hit[..., 0]) for space, p in candidates.items()}
        best = max(fits, key=fits.get)
        other = next((space for space in fits if space != best), None)
        if fits[best] < PERSPECTIVE_FIT_MIN:
            which = "either" if other else "the camera frame, and the file has no worldToCamera"
            raise NormalSpaceError(
                f"{path}: cannot tell whether its positions and normals are in camera or world space (they follow no "
                f"perspective camera of {which}); "
                f"declare it with --normal-space camera|world (pbrt-v4's gbuffer film writes camera space unless "
                f'"string coordinatesystem" "world")'
            )
        found.normal_space = best
        note = (
            f"{path.name}: positions and normals are in {best} space ({fits[best]:.0%} of the pixels lie on "
            f"their pixel's ray" + (f", {fits[other]:.0%} in {other} space)" if other else ")")
        )
    else:
        note = ""
    camera_position = candidates.get(found.normal_space, position)
    depth = np.where(hit, np.linalg.norm(camera_position, axis=-1, keepdims=True), 0.0).astype(np.float32)
    return depth, hit.astype(np.float32), note


def _perspective_fit(position: np.ndarray, hit: np.ndarray) -> float:
    """The share of pixels whose camera-space position lies on the pixel's ray: x/z a linear function of
    the column and y/z of the row (fitted on the best 80%, so pixels that mix two surfaces, whose mean
    position lies off every ray, do not spoil the fit). A wrong frame puts few pixels on any such line."""
    rows, cols = np.nonzero(hit)
    if rows.size < 16:
        return 0.0
    p = position[rows, cols].astype(np.float64)
    z = p[:, 2]
    if np.mean(z > 0) < 0.99:
        return 0.0
    on_ray = np.ones(rows.size, bool)
    for coordinate, pixel in ((p[:, 0] / np.where(z > 0, z, 1), cols), (p[:, 1] / np.where(z > 0, z, 1), rows)):
        if np.ptp(pixel) == 0:
            return 0.0
        keep = np.ones(rows.size, bool)
        for _ in range(2):
            slope, intercept = np.polyfit(pixel[keep], coordinate[keep], 1)
            residual = np.abs(coordinate - (slope * pixel + intercept))
            keep = residual <= np.percentile(residual, 80)
        on_ray &= residual < PERSPECTIVE_TOLERANCE * abs(slope)
    return float(on_ray.mean())
