"""Print what each Table 1 metric costs per image: wall and CPU seconds of one score, median over repeats,
the metrics taking turns run by run (a busy machine slows them alike), and each one's ratio to 1-SSIM.

    .venv/bin/python benchmarks/bench_metrics.py [--size 256x256] [--repeats 5]

The pair is a noisy HDR image against its reference (gamma-distributed radiance with 10 % noise): the
metrics' cost does not depend on the content, except HDR-FLIP's, which runs one LDR-FLIP per exposure
of the reference's range (4 here, as on the rendered test scenes).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from admc.common.metrics import METRICS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="256x256", help="WIDTHxHEIGHT")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    width, height = map(int, args.size.split("x"))
    rng = np.random.default_rng(0)
    ref = rng.gamma(1.0, 0.5, (height, width, 3)).astype(np.float32)
    x = np.maximum(ref * (1 + 0.1 * rng.normal(size=ref.shape)), 0).astype(np.float32)
    for m in METRICS:  # warm-up: imports, caches
        m.compute(x, ref)
    wall, cpu = {m.key: [] for m in METRICS}, {m.key: [] for m in METRICS}
    for _ in range(args.repeats):
        for m in METRICS:
            w, c = time.perf_counter(), time.process_time()
            m.compute(x, ref)
            wall[m.key].append(time.perf_counter() - w)
            cpu[m.key].append(time.process_time() - c)
    base = statistics.median(cpu["one_minus_ssim"])
    print(f"{width}x{height}, median of {args.repeats}")
    for m in METRICS:
        c = statistics.median(cpu[m.key])
        print(
            f"  {m.label:9s} wall {statistics.median(wall[m.key]):8.4f} s  cpu {c:8.4f} s  "
            f"({c / base:6.1f}x 1-SSIM's cpu)"
        )


if __name__ == "__main__":
    main()
