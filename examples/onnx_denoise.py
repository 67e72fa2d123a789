"""Denoise a render with admc's exported graphs, following admc.json and nothing else.

    admc-pipe export weights/admc-small-pretrained.pt -o admc-onnx
    python examples/onnx_denoise.py admc-onnx render.exr denoised.exr

A reference for running admc inside a renderer: it imports NumPy, SciPy, ONNX Runtime and OpenEXR (and
pyoidn for an admc+oidn export), nothing of admc, so every step is one a renderer's own code takes, with
its constants read from admc.json (docs/engines.md spells each out). tests/test_export_consumer.py checks
that it gives what `admc-pipe denoise --engine onnxruntime` gives.

Input: a multi-layer EXR with admc's layer names, as `admc-pipe render` writes (diffuse.R, specular.R,
albedo.R, normal.X, depth.Z, coverage.A; diffuse_var.R and specular_var.R if the renderer has them).
Output: the image as R, G, B and the denoised diffuse.* and specular.* layers, float32. admc's optional
extras (the self-ensemble, the dark pass) are left out, as `denoise` leaves them out by default.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import onnxruntime
import OpenEXR
from scipy.ndimage import uniform_filter

CHANNELS = {
    "diffuse": "RGB",
    "specular": "RGB",
    "albedo": "RGB",
    "normal": "XYZ",
    "depth": "Z",
    "coverage": "A",
    "diffuse_var": "RGB",
    "specular_var": "RGB",
}
REQUIRED = ("diffuse", "albedo", "normal")


def oidn_with_weights(color, albedo, normal, weights: bytes, clean_aux: bool = False) -> np.ndarray:
    """OIDN (hdr, quality high) running the network weights of a TZA archive: OIDN's C API takes them as the
    filter's "weights" data, a call pyoidn does not declare, so it is declared here. `clean_aux`: the guides
    were prefiltered (`oidn_prefilter`)."""
    from pyoidn.capi import oidn_Capi, oidn_ffi
    from pyoidn.device import Device
    from pyoidn.filter import OIDN_FORMAT_FLOAT3, OIDN_QUALITY_HIGH, Filter

    if not getattr(oidn_ffi, "_weights_declared", False):
        oidn_ffi.cdef("void oidnSetSharedFilterData(OIDNFilter filter, const char* name, void* ptr, size_t size);")
        oidn_ffi._weights_declared = True
    height, width = color.shape[:2]
    output = np.zeros((height, width, 3), np.float32)
    device = Device()
    device.commit()
    blob = oidn_ffi.from_buffer(weights)
    with Filter(device) as oidn_filter:
        for name, image in (("color", color), ("albedo", albedo), ("normal", normal), ("output", output)):
            if image is not None:
                oidn_filter.set_image(name, np.ascontiguousarray(image, np.float32), OIDN_FORMAT_FLOAT3, width, height)
        oidn_filter.set_bool("hdr", True)
        oidn_filter.set_bool("cleanAux", clean_aux)
        oidn_filter.set_quality(OIDN_QUALITY_HIGH)
        oidn_Capi.oidnSetSharedFilterData(oidn_filter._filter, b"weights", blob, len(weights))
        oidn_filter.commit()
        oidn_filter.execute()
    device.release()
    return output


def oidn_prefilter(name: str, image: np.ndarray) -> np.ndarray:
    """OIDN's own denoising of an "albedo" or "normal" guide (quality high), for weights that take clean guides."""
    from pyoidn.device import Device
    from pyoidn.filter import OIDN_FORMAT_FLOAT3, OIDN_QUALITY_HIGH, Filter

    height, width = image.shape[:2]
    output = np.zeros((height, width, 3), np.float32)
    device = Device()
    device.commit()
    with Filter(device) as oidn_filter:
        oidn_filter.set_image(name, np.ascontiguousarray(image, np.float32), OIDN_FORMAT_FLOAT3, width, height)
        oidn_filter.set_image("output", output, OIDN_FORMAT_FLOAT3, width, height)
        oidn_filter.set_quality(OIDN_QUALITY_HIGH)
        oidn_filter.commit()
        oidn_filter.execute()
    device.release()
    return output


def read_layers(path: Path) -> dict[str, np.ndarray]:
    """The admc layers an EXR holds, as float32 (H, W, C)."""
    if not Path(path).is_file():
        raise ValueError(f"{path}: no such file")
    pixels = OpenEXR.File(str(path), separate_channels=True).channels()
    layers = {
        name: np.stack([pixels[f"{name}.{c}"].pixels.astype(np.float32) for c in channels], axis=-1)
        for name, channels in CHANNELS.items()
        if all(f"{name}.{c}" in pixels for c in channels)
    }
    missing = [name for name in REQUIRED if name not in layers]
    if missing:
        raise ValueError(f"{path}: lacks layer(s) {', '.join(missing)}")
    return layers


def write_image(path: Path, planes: dict[str, np.ndarray]) -> None:
    """`planes` ("" for the image itself) as float32 R, G, B channels."""
    channels = {
        (f"{name}.{c}" if name else c): np.ascontiguousarray(image[..., i], dtype=np.float32)
        for name, image in planes.items()
        for i, c in enumerate("RGB")
    }
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(str(path))


def sanitize(x: np.ndarray, rule: dict) -> np.ndarray:
    """NaN -> rule's nan, -Inf -> min, +Inf -> max (nan when there is no max), finite values clipped."""
    low, high = rule["min"], rule["max"]
    x = np.where(np.isnan(x), rule["nan"], x)
    x = np.where(np.isposinf(x), rule["nan"] if high is None else high, x)
    return np.clip(x, low, high).astype(np.float32)


class ExportedAdmc:
    """admc.json and its graphs, run as the JSON says."""

    def __init__(self, folder: Path) -> None:
        manifest = Path(folder) / "admc.json"
        if not manifest.is_file():
            raise ValueError(f"{folder}: holds no admc.json (write the folder with `admc-pipe export`)")
        self.folder = Path(folder)
        self.spec = json.loads(manifest.read_text())
        if self.spec.get("format") != "admc-onnx" or self.spec.get("version") != 4:
            raise ValueError(f"{manifest}: not an admc-onnx export of version 4 (export it again with this admc)")
        self.sessions = {
            branch: onnxruntime.InferenceSession(str(Path(folder) / graph), providers=["CPUExecutionProvider"])
            for branch, graph in self.spec["graphs"].items()
        }

    def __call__(self, layers: dict[str, np.ndarray], tile: int = 320) -> dict[str, np.ndarray]:
        """The image ("") and the denoised branches of one render's layers, linear HDR (H, W, 3)."""
        spec, transform = self.spec, self.spec["transform"]
        height, width = layers["diffuse"].shape[:2]
        # 1. fill missing layers, sanitise (admc.json: missing, transform.sanitize, variance)
        for name, value in spec["missing"].items():
            if name != "rule" and name not in layers:
                layers = {**layers, name: np.full((height, width, 1), value, np.float32)}
        clean = {
            name: sanitize(layers[name], transform["sanitize"][name])
            for name in transform["sanitize"]
            if name in layers
        }
        variance = {
            branch: sanitize(layers[name], spec["variance"]["sanitize"])
            for branch, name in spec["variance"]["layers"].items()
            if name in layers and branch in clean
        }
        branches = [b for b in ("diffuse", "specular") if b in clean and b in self.sessions]
        # 2. exposure normalisation and the graphs' inputs (exposure, transform, inputs, noise_std_unit, base)
        gain = self.exposure_gain(clean["diffuse"] + clean.get("specular", 0.0))
        exposed = {b: clean[b] * np.float32(gain) for b in branches}
        scale = {"diffuse": np.clip(clean["albedo"], 0.0, 1.0) + np.float32(spec["eps"]), "specular": np.float32(1.0)}
        log_noisy = {b: np.log1p(np.clip(exposed[b], 0.0, transform["radiance_max"]) / scale[b]) for b in branches}
        features = self.features(clean)
        inputs = {b: {"noisy": log_noisy[b], "features": features} for b in branches}
        if spec.get("noise_input"):
            for b in branches:
                if b not in variance:
                    raise ValueError(f"the input lacks {spec['variance']['layers'][b]}, which this export reads")
                inputs[b]["noise"] = self.noise_map(variance[b] * np.float32(gain) ** 2, exposed[b], scale[b])
        if spec["base"] != "noisy":
            for b, base in self.oidn_bases(exposed, clean, spec["base_quality"]).items():
                inputs[b]["base"] = np.log1p(np.clip(base, 0.0, transform["radiance_max"]) / scale[b])
        # 3. the graphs, tiled; clamp, environment pixels, inverse (tile, output)
        environment = clean["coverage"] == 0
        out = {}
        for b in branches:
            log = np.nan_to_num(self.run_tiled(b, inputs[b], tile), nan=0.0, posinf=0.0, neginf=0.0)
            log = np.clip(log, 0.0, spec["output"]["log_max"][b])
            log = np.where(environment, log_noisy[b], log)
            out[b] = (np.expm1(log) * scale[b] / np.float32(gain)).astype(np.float32)
        if "specular" in clean and "specular" not in out:
            out["specular"] = clean["specular"]  # no specular graph: the input passes through
        # 3b. blended with OIDN's output where the weights ship shares (oidn_blend)
        blend = spec.get("oidn_blend")
        if blend:
            weights = {b: self.folder / name for b, name in blend.get("weights", {}).items()}
            prefiltered = blend.get("prefiltered_guides", [])
            oidn = self.oidn_bases({b: clean[b] for b in branches}, clean, blend["quality"], weights, prefiltered)
            for b, share in blend["shares"].items():
                if b in branches:
                    out[b] = (np.float32(share) * out[b] + np.float32(1 - share) * oidn[b]).astype(np.float32)
        # 4. back toward the input where it is resolved (keep_resolved)
        before = out["diffuse"] + out.get("specular", 0.0)
        for b in branches:
            if b in variance:
                out[b] = self.keep_resolved(out[b], clean[b], variance[b], before)
        return {"": out["diffuse"] + out.get("specular", 0.0), **out}

    def exposure_gain(self, radiance: np.ndarray) -> float:
        rule = self.spec["exposure"]
        luminance = radiance @ np.float32(rule["luminance"])
        lit = luminance[np.isfinite(luminance) & (luminance > rule["lit"])]
        level = float(np.exp(np.mean(np.log(lit)))) if lit.size else 0.0
        if level <= 0.0 or level >= rule["trained_brightness"]:
            return 1.0
        steps = round(math.log2(rule["trained_brightness"] / level))
        peak = float(radiance.max())
        if peak > 0:
            steps = min(steps, math.floor(math.log2(self.spec["transform"]["radiance_max"] / peak)))
        return 2.0 ** max(steps, 0)

    def features(self, clean: dict[str, np.ndarray]) -> np.ndarray:
        """normal.XYZ, depth, albedo.RGB, in the order admc.json's `inputs.features` lists them."""
        assert self.spec["inputs"]["features"][:4] == ["normal.X", "normal.Y", "normal.Z", "depth"]
        depth, hit = clean["depth"], (clean["coverage"] > 0) & (clean["depth"] > 0)
        relative = np.ones_like(depth)
        if hit.any():
            relative[hit] = np.clip(depth[hit] / np.float64(depth[hit].max()), 0.0, 1.0)
        normal = np.clip((clean["normal"] + np.float32(1.0)) * np.float32(0.5), 0.0, 1.0)
        return np.concatenate([normal, relative, np.clip(clean["albedo"], 0.0, 1.0)], axis=-1)

    def noise_map(self, variance: np.ndarray, radiance: np.ndarray, scale) -> np.ndarray:
        unit = self.spec["noise_std_unit"]
        std = np.sqrt(variance.astype(np.float64)) / (np.clip(radiance, 0.0, None).astype(np.float64) + scale)
        return (np.log1p(std.mean(axis=-1, keepdims=True) / unit) / np.log1p(1.0 / unit)).astype(np.float32)

    def oidn_bases(
        self,
        images: dict[str, np.ndarray],
        clean: dict[str, np.ndarray],
        quality: dict[str, str],
        weights: dict[str, Path] | None = None,
        prefiltered: list[str] = (),
    ) -> dict[str, np.ndarray]:
        """OIDN on each branch (diffuse with albedo and normal, specular alone) at each branch's quality, with
        the weights file a branch names (a TZA archive: OIDN fine-tuned with the model) instead of its own, on
        guides OIDN prefiltered for the branches in `prefiltered`."""
        import pyoidn

        guides = {"diffuse": (clean["albedo"], clean["normal"]), "specular": (None, None)}
        for b in prefiltered:
            guides[b] = (oidn_prefilter("albedo", guides[b][0]), oidn_prefilter("normal", guides[b][1]))
        weights = weights or {}
        return {
            b: np.nan_to_num(
                oidn_with_weights(image, *guides[b], weights[b].read_bytes(), b in prefiltered)
                if b in weights
                else pyoidn.denoise(image, *guides[b], hdr=True, quality=quality[b]),
                nan=0.0,
                posinf=0.0,
                neginf=0.0,
            ).clip(0.0, None)
            for b, image in images.items()
        }

    def run_tiled(self, branch: str, inputs: dict[str, np.ndarray], tile: int) -> np.ndarray:
        """The branch's graph over cores of at most `tile` pixels, each run with `halo` pixels of image around
        it and started on a multiple of `alignment`: the same as one run on the whole image."""
        halo, align = self.spec["tile"]["halo"], self.spec["tile"]["alignment"]
        height, width = inputs["noisy"].shape[:2]
        out = np.empty((height, width, 3), np.float32)
        for top in range(0, height, tile):
            for left in range(0, width, tile):
                rows = slice(top, min(top + tile, height))
                cols = slice(left, min(left + tile, width))
                y0, x0 = max(top - halo, 0), max(left - halo, 0)
                y0, x0 = y0 - y0 % align, x0 - x0 % align
                crop = (slice(y0, min(rows.stop + halo, height)), slice(x0, min(cols.stop + halo, width)))
                feeds = {name: np.ascontiguousarray(a[crop].transpose(2, 0, 1)[None]) for name, a in inputs.items()}
                result = self.sessions[branch].run(None, feeds)[0][0].transpose(1, 2, 0)
                out[rows, cols] = result[top - y0 : rows.stop - y0, left - x0 : cols.stop - x0]
        return out

    def keep_resolved(self, out: np.ndarray, noisy: np.ndarray, variance: np.ndarray, image: np.ndarray) -> np.ndarray:
        rule = self.spec["keep_resolved"]
        size = 2 * rule["radius"] + 1

        def box(x):
            return uniform_filter(x, size, mode="reflect")

        def mean(x):
            return (x[..., 0] + x[..., 1] + x[..., 2]) * np.float32(1.0 / 3.0)

        s = np.square(mean(image)) + np.float32(rule["relmse_eps"])
        v = np.maximum(box(mean(variance) / s), 0.0)
        silent = np.all(variance <= 0, axis=-1).astype(np.float32)
        resolved = (v < rule["converged"]) & (box(silent) <= rule["unsampled"])
        b = box(mean(np.square(out - noisy)) / s) - v * np.float32(1.0 + rule["margin"] * math.sqrt(2.0) / size)
        w = np.where(resolved & (b > 0), b / np.maximum(b + v, 1e-30), 0.0)
        return out + np.clip(w, 0.0, 1.0).astype(np.float32)[..., None] * (noisy - out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("export", type=Path, help="folder written by `admc-pipe export`")
    parser.add_argument("input", type=Path, help="multi-layer EXR with admc's layer names")
    parser.add_argument("output", type=Path, help="EXR to write")
    parser.add_argument("--tile", type=int, default=320, help="largest core edge run at once (bounds memory)")
    args = parser.parse_args()
    try:
        planes = ExportedAdmc(args.export)(read_layers(args.input), tile=args.tile)
    except ValueError as error:
        parser.exit(1, f"error: {error}\n")
    write_image(args.output, planes)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
