"""The `admc_split` Mitsuba integrator: every buffer the denoiser needs, in one render pass.

It is Mitsuba's `path` integrator (emitter + BSDF sampling with MIS, the same Russian roulette,
the same order of random numbers, so equal seeds give near-identical images) with the radiance
split into `diffuse` and `specular` by the KPCN rule, plus per-sample features and second moments
written as AOVs. The film (box filter) averages the AOVs per pixel; `render_buffers` turns those
averages into the arrays the rest of the pipeline stores.

Split rule: delta vertices (mirror, smooth glass, null) are followed. At the first non-delta
vertex, next-event estimation is split exactly by evaluating the BSDF with a diffuse-only context
(diffuse part -> `diffuse`, remainder -> `specular`), and the lobe the BSDF sample picks there sends
the whole rest of the path to one buffer. Emission reached before that vertex goes to `diffuse`.
Features (albedo, shading normal, depth) are taken at that vertex, times the delta chain's
throughput; a chain that escapes to the environment has albedo = its throughput, no normal, no depth.
Albedo is the diffuse reflectance where the BSDF has a diffuse lobe: it is exact per
sample, so demodulating the diffuse buffer by it adds no noise (the BSDF sample weight of a rough
plastic is a noisy estimate: which lobe was picked, which direction). Elsewhere it is the sample
weight, so conductors and dielectrics get a real albedo (Mitsuba's `eval_diffuse_reflectance` is 0
for smooth ones and f * pi at normal incidence for rough ones, 6.0 for rough gold); their diffuse
buffer is empty anyway. A BSDF that reports no diffuse reflectance of its own but has a diffuse lobe
(a `blendbsdf` of diffuse and metal) gets that default too: noise-free, the same in training and
inference, clipped to 1 by the transforms, but not a physical albedo.

Coverage is the share of a pixel's samples that reached a non-delta vertex; where none did but its
samples disagree (`_samples_disagree`), the share that escaped to the environment after a delta
vertex. Inference passes pixels of coverage 0 through as environment seen directly, which has no
noise; the sky in a mirror sphere or through glass is as noisy as the surface is curved, so those
pixels get a coverage and are denoised. Where their samples agree (a black void through glass, a
uniform sky in a mirror; always at 1 spp) there is nothing to denoise, and denoising them anyway made
admc's relMSE worse on studio scenes of glass in a black void. The covered ones keep the features
they always had: the networks train on every pixel, these included, and giving them the mirror's
normal and depth instead made the shipped admc smooth the reflected sky (4.8x the noisy input's
relMSE at 64 spp on experiments/delta_paths_check.py's mirror spheres).

The sampling loop is a Dr.Jit symbolic loop (`@dr.syntax`): in JIT variants the whole wavefront
compiles into one kernel, which is what makes a Python integrator as fast as the C++ `path`.
"""

from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi
import numpy as np

from admc.common.buffers import LAYERS
from admc.common.layout import BRANCHES

INTEGRATOR_NAME = "admc_split"


def aov_layout(split: bool) -> list[tuple[str, tuple[str, ...]]]:
    """Per-sample AOVs in the order the integrator writes them: (buffer name, channel suffixes)."""
    radiance = BRANCHES if split else BRANCHES[:1]
    return (
        [(name, LAYERS[name].channels) for name in (*radiance, "albedo", "normal", "depth", "coverage")]
        + [(f"{name}_m2", LAYERS[name].channels) for name in radiance]
        + [("delta_coverage", LAYERS["coverage"].channels)]
    )


def _aov_channel_names(split: bool) -> list[str]:
    return [f"{name}.{c}" for name, channels in aov_layout(split) for c in channels]


def _mis_weight(pdf_a, pdf_b):
    """Power heuristic, 0 where it is not finite (as Mitsuba's `path` computes it)."""
    a2 = dr.square(pdf_a)
    w = a2 / (a2 + dr.square(pdf_b))
    return dr.select(dr.isfinite(w), w, 0.0)


@functools.cache
def _integrator_class(variant: str) -> type:
    """Build the integrator class for the active variant (mi.SamplingIntegrator is per variant).

    Long on purpose: the class must be defined after the variant is set, so its methods live in here."""

    class AdmcSplitIntegrator(mi.SamplingIntegrator):
        """Path tracer with KPCN diffuse/specular split, features and second moments as AOVs."""

        def __init__(self, props: mi.Properties):
            super().__init__(props)
            max_depth = int(props.get("max_depth", 8))
            rr_depth = int(props.get("rr_depth", 5))
            if max_depth < -1:
                raise ValueError(f"{INTEGRATOR_NAME}: max_depth must be -1 (unbounded) or >= 0, got {max_depth}")
            if rr_depth <= 0:
                raise ValueError(f"{INTEGRATOR_NAME}: rr_depth must be > 0, got {rr_depth}")
            self.max_depth = 0xFFFFFFFF if max_depth == -1 else max_depth
            self.rr_depth = rr_depth
            self.split = bool(props.get("split", True))

        def aov_names(self) -> list[str]:
            return _aov_channel_names(self.split)

        def to_string(self) -> str:
            return f"AdmcSplitIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, split={self.split}]"

        @dr.syntax
        def sample(self, scene, sampler, ray, medium=None, active=True):
            # Long on purpose, like Mitsuba's own path tracer: @dr.syntax turns the while loop below into a
            # Dr.Jit loop whose state is every local the body changes; helpers would pass it all in and out.
            split = self.split
            bsdf_ctx = mi.BSDFContext()
            diffuse_ctx = mi.BSDFContext()
            diffuse_ctx.type_mask = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.DiffuseTransmission

            ray = mi.Ray3f(ray)
            depth = mi.UInt32(0)
            throughput = mi.Spectrum(1.0)
            eta = mi.Float(1.0)
            active = mi.Bool(active) & (self.max_depth > 0)
            valid_ray = mi.Bool(scene.environment() is not None)

            prev_si = dr.zeros(mi.Interaction3f)
            prev_bsdf_pdf = mi.Float(1.0)
            prev_bsdf_delta = mi.Bool(True)

            l_diffuse = mi.Spectrum(0.0)
            l_specular = mi.Spectrum(0.0)
            found = mi.Bool(False)  # first non-delta vertex reached (and processed)
            to_specular = mi.Bool(False)  # lobe sampled there was not diffuse
            albedo = mi.Spectrum(0.0)
            normal = mi.Vector3f(0.0)
            distance = mi.Float(0.0)
            delta_seen = mi.Bool(False)  # the chain met a mirror or smooth glass
            delta_escape = mi.Bool(False)  # ... and then escaped to the environment

            while dr.hint(active, label=INTEGRATOR_NAME):
                si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0))
                hit = si.is_valid()
                in_chain = ~found
                into_specular = found & to_specular

                # ---- Emission hit by the previous BSDF sample (or seen through delta chains)
                ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                on_emitter = ds.emitter != None  # noqa: E711 (Dr.Jit pointer comparison)
                em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
                emitted = ds.emitter.eval(si, prev_bsdf_pdf > 0.0) * _mis_weight(prev_bsdf_pdf, em_pdf)
                if dr.hint(split, mode="scalar"):
                    l_specular[into_specular] = dr.fma(throughput, emitted, l_specular)
                    l_diffuse[~into_specular] = dr.fma(throughput, emitted, l_diffuse)
                else:
                    l_diffuse = dr.fma(throughput, emitted, l_diffuse)

                active_next = (depth + 1 < self.max_depth) & hit
                bsdf = si.bsdf(ray)
                smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                first = in_chain & hit & smooth
                distance[in_chain & hit] += si.t
                albedo[in_chain & ~hit] = throughput
                delta_escape |= in_chain & ~hit & delta_seen
                delta_seen |= in_chain & hit & ~smooth & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)

                # ---- Emitter sampling (same random numbers as `path`)
                active_em = active_next & smooth
                ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
                active_em &= ds.pdf != 0.0
                wo = si.to_local(ds.d)

                sample_1 = sampler.next_1d()
                sample_2 = sampler.next_2d()
                bsdf_val, bsdf_pdf, bs, bsdf_weight = bsdf.eval_pdf_sample(bsdf_ctx, si, wo, sample_1, sample_2)

                mis_em = dr.select(ds.delta, 1.0, _mis_weight(ds.pdf, bsdf_pdf))
                nee = bsdf_val * em_weight * mis_em
                if dr.hint(split, mode="scalar"):
                    diffuse_val = bsdf.eval(diffuse_ctx, si, wo, active_em & first)
                    nee_diffuse = dr.select(first, diffuse_val * em_weight * mis_em, dr.select(into_specular, 0.0, nee))
                    l_diffuse[active_em] = dr.fma(throughput, nee_diffuse, l_diffuse)
                    l_specular[active_em] = dr.fma(throughput, nee - nee_diffuse, l_specular)
                else:
                    l_diffuse[active_em] = dr.fma(throughput, nee, l_diffuse)

                # ---- Features at the first non-delta vertex
                has_diffuse = mi.has_flag(bsdf.flags(), mi.BSDFFlags.DiffuseReflection)
                reflectance = dr.select(
                    has_diffuse, bsdf.eval_diffuse_reflectance(si, first & has_diffuse), bsdf_weight
                )
                albedo[first] = throughput * dr.select(on_emitter, 1.0, reflectance)
                normal[first] = si.sh_frame.n
                to_specular[first] = ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
                found |= first

                # ---- BSDF sampling and path state, exactly as `path`
                ray = si.spawn_ray(si.to_world(bs.wo))
                throughput *= bsdf_weight
                eta *= bs.eta
                valid_ray |= hit & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
                prev_si = mi.Interaction3f(si)
                prev_bsdf_pdf = bs.pdf
                prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

                depth[hit] += 1
                throughput_max = dr.max(throughput)
                rr_prob = dr.minimum(throughput_max * dr.square(eta), 0.95)
                rr_active = depth >= self.rr_depth
                rr_continue = sampler.next_1d() < rr_prob
                throughput[rr_active] *= dr.rcp(rr_prob)
                active = active_next & (~rr_active | rr_continue) & (throughput_max != 0.0)

            coverage = dr.select(found, 1.0, 0.0)
            radiance = [l_diffuse, l_specular] if split else [l_diffuse]
            aovs = []
            for buffer in radiance:
                aovs += [buffer.x, buffer.y, buffer.z]
            aovs += [albedo.x, albedo.y, albedo.z, normal.x, normal.y, normal.z]
            aovs += [dr.select(found, distance, 0.0), coverage]
            for buffer in radiance:
                aovs += [dr.square(buffer.x), dr.square(buffer.y), dr.square(buffer.z)]
            aovs += [dr.select(delta_escape, 1.0, 0.0)]
            return l_diffuse + l_specular, valid_ray, aovs

    return AdmcSplitIntegrator


SAMPLES_AGREE_RTOL = 1e-3
"""A pixel's samples agree where their standard deviation is below this share of their mean in every
channel of every radiance buffer (float32 accumulation leaves about 2e-4 on identical samples)."""


def _samples_disagree(buffers: dict[str, np.ndarray], spp: int) -> np.ndarray:
    """(H, W, 1): the pixel's samples differ beyond float rounding in some radiance channel."""
    spread = [
        buffers[f"{name}_var"] * spp > np.square(SAMPLES_AGREE_RTOL * buffers[name])
        for name in BRANCHES
        if name in buffers
    ]
    return np.any(np.concatenate(spread, axis=-1), axis=-1, keepdims=True)


_registered_variants: set[str] = set()


def register() -> None:
    """Register `admc_split` for the active variant (idempotent; call after mi.set_variant).

    Only JIT RGB variants: the buffers are RGB, and in scalar variants a Python integrator runs
    once per sample (two orders of magnitude slower) and must not touch a missed ray's BSDF.
    """
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("register(): no Mitsuba variant is active; call use_variant() first")
    if not (variant.endswith("_rgb") and variant.split("_")[0] in ("llvm", "cuda")):
        raise RuntimeError(
            f"{INTEGRATOR_NAME} needs a JIT RGB variant (llvm_ad_rgb, cuda_ad_rgb), the active one is {variant!r}"
        )
    if variant in _registered_variants:
        return
    cls = _integrator_class(variant)
    mi.register_integrator(INTEGRATOR_NAME, lambda props: cls(props))
    _registered_variants.add(variant)


def pass_seeds(seed: int, n_passes: int) -> list[int]:
    """One 32-bit seed per pass, hashed from `seed` (not seed + i, which would make the renders of
    neighbouring seeds share passes and so correlate them)."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(n_passes, dtype=np.uint32)]


def _split_passes(spp: int, max_spp_per_pass: int) -> list[int]:
    n_passes = -(-spp // max_spp_per_pass)
    base, extra = divmod(spp, n_passes)
    return [base + (1 if i < extra else 0) for i in range(n_passes)]


def render_buffers(
    scene: "mi.Scene", spp: int, seed: int, *, split: bool = True, max_depth: int = 8, max_spp_per_pass: int = 256
) -> dict[str, np.ndarray]:
    """Render all denoiser buffers of `scene` at `spp` samples per pixel, as float32 (H, W, C) arrays.

    Large spp are rendered in passes of at most `max_spp_per_pass` (memory is per pass), each with
    its own seed, and combined exactly: means and second moments weighted by the pass spp.
    """
    if spp < 1:
        raise ValueError(f"render_buffers: spp must be >= 1, got {spp}")
    if max_spp_per_pass < 1:
        raise ValueError(f"render_buffers: max_spp_per_pass must be >= 1, got {max_spp_per_pass}")
    if seed < 0:
        raise ValueError(f"render_buffers: seed must be >= 0, got {seed}")
    rfilter = scene.sensors()[0].film().rfilter().class_name()
    if rfilter != "BoxFilter":
        raise ValueError(
            f"render_buffers: the scene's film uses a {rfilter}; per-pixel means and variances "
            "need a box reconstruction filter ('rfilter': {'type': 'box'})"
        )
    register()
    integrator = mi.load_dict({"type": INTEGRATOR_NAME, "split": split, "max_depth": max_depth})
    layout = aov_layout(split)
    n_aov = sum(len(channels) for _, channels in layout)

    passes = _split_passes(spp, max_spp_per_pass)
    total = None
    for pass_spp, pass_seed in zip(passes, pass_seeds(seed, len(passes))):
        image = np.asarray(mi.render(scene, integrator=integrator, spp=pass_spp, seed=pass_seed), dtype=np.float64)
        if image.ndim != 3 or image.shape[2] < n_aov:
            raise RuntimeError(f"render_buffers: film returned shape {image.shape}, expected >= {n_aov} AOV channels")
        weighted = image[:, :, image.shape[2] - n_aov :] * pass_spp
        total = weighted if total is None else total + weighted
    mean = total / spp

    planes, offset = {}, 0
    for name, channels in layout:
        planes[name] = mean[:, :, offset : offset + len(channels)]
        offset += len(channels)

    out = {}
    for name in BRANCHES if split else BRANCHES[:1]:
        m1 = planes[name]
        out[name] = m1
        out[f"{name}_var"] = np.maximum(planes[f"{name}_m2"] - np.square(m1), 0.0) / spp
    via_delta = (planes["coverage"] == 0) & (planes["delta_coverage"] > 0) & _samples_disagree(out, spp)
    coverage = np.where(via_delta, planes["delta_coverage"], planes["coverage"])
    out.update(
        {
            "albedo": planes["albedo"],
            "normal": planes["normal"],
            "depth": np.where(coverage > 0, planes["depth"] / np.where(coverage > 0, coverage, 1.0), 0.0),
            "coverage": coverage,
        }
    )
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}
