"""Samples per second of the admc_split integrator (all buffers, variance included) against Mitsuba's `path`.

Same scene (Cornell box with a glossy sphere), variant, spp and max_depth; each integrator gets a
warm-up render first (kernel compilation is not measured), then the median of --repeats renders,
alternating between the two. CPU time is printed too: on a shared machine it is the steadier figure.

    .venv/bin/python benchmarks/bench_integrator.py --size 128 --spp 64 --variant auto
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from admc.pipeline.render.variants import use_variant


def glossy_cornell_box(mi, size: int):
    scene = mi.cornell_box()
    scene.pop("integrator")
    scene["sensor"]["film"] = {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}
    scene["glossy-sphere"] = {
        "type": "sphere",
        "center": [0.35, -0.55, 0.3],
        "radius": 0.3,
        "bsdf": {"type": "roughconductor", "material": "Cu", "alpha": 0.15},
    }
    return mi.load_dict(scene)


def interleaved_timings(renders: dict, repeats: int) -> dict[str, tuple[float, float]]:
    """Median (wall, CPU) seconds per render; the integrators alternate so that load from other
    processes on a shared machine hits them alike. One warm-up render each (JIT compilation)."""
    for render in renders.values():
        render(0)
    wall = {name: [] for name in renders}
    cpu = {name: [] for name in renders}
    for seed in range(1, repeats + 1):
        for name, render in renders.items():
            start_wall, start_cpu = time.perf_counter(), time.process_time()
            render(seed)
            wall[name].append(time.perf_counter() - start_wall)
            cpu[name].append(time.process_time() - start_cpu)
    return {name: (statistics.median(wall[name]), statistics.median(cpu[name])) for name in renders}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128, help="image width and height")
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel")
    parser.add_argument("--variant", default="auto", help="Mitsuba variant or 'auto'")
    parser.add_argument("--max-depth", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5, help="timed renders per integrator (median reported)")
    args = parser.parse_args()

    variant = use_variant(args.variant)
    import mitsuba as mi

    from admc.pipeline.render.integrator import render_buffers

    scene = glossy_cornell_box(mi, args.size)
    path = mi.load_dict({"type": "path", "max_depth": args.max_depth})
    samples = args.size * args.size * args.spp

    def render_path(seed: int) -> None:
        np.asarray(mi.render(scene, integrator=path, spp=args.spp, seed=seed))

    def render_admc(seed: int) -> None:
        render_buffers(scene, args.spp, seed, split=True, max_depth=args.max_depth)

    timings = interleaved_timings({"path": render_path, "admc_split": render_admc}, args.repeats)
    print(
        f"variant {variant}, {args.size}x{args.size}, {args.spp} spp, max_depth {args.max_depth}, "
        f"median of {args.repeats} interleaved renders"
    )
    for name, (wall, cpu) in timings.items():
        print(
            f"{name:10s} {samples / wall / 1e6:6.2f} M samples/s wall ({wall * 1e3:7.1f} ms), "
            f"{samples / cpu / 1e6:6.2f} M samples/s per CPU-second ({cpu * 1e3:7.1f} ms CPU)"
        )
    (path_wall, path_cpu), (admc_wall, admc_cpu) = timings["path"], timings["admc_split"]
    print(
        f"ratio admc_split / path (samples/s): wall {path_wall / admc_wall:.2f}x, CPU {path_cpu / admc_cpu:.2f}x "
        "(admc_split includes all buffers, variance and the NumPy assembly)"
    )


if __name__ == "__main__":
    main()
