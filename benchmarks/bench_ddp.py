"""Data-parallel training: the time of one global step in 1..N processes at the same global batch.

A small patch store is rendered once; then for each process count, `train` runs in that many processes
(admc's own launcher, as `admc-pipe train --nproc N`; gloo on the CPU with --threads threads each, nccl
with one process per GPU on CUDA) for 2 x WINDOW steps, and the step time is read from the second
logged window of metrics.csv (the first holds start-up and the first steps' allocations).
One thread per process by default: on a CPU that other jobs share, one process with two OpenMP
threads was measured ~30x slower than with one (spinning threads), which is not what DDP changes.

    python benchmarks/bench_ddp.py                                   # 1 and 2 processes, the default small model
    python benchmarks/bench_ddp.py --nproc 1 2 --batch 8 --window 20 --precision bfloat16
    python benchmarks/bench_ddp.py --device cuda --nproc 1           # one process per GPU the machine has
"""

import argparse
import csv
import dataclasses
import tempfile
from pathlib import Path


from admc.model.precision import resolve_device
from admc.model.training import distributed
from admc.model.training.trainer import train
from admc.pipeline.config import load_config
from admc.pipeline.render.variants import use_variant
from admc.pipeline.stages.dataset import build_dataset

STORE = [
    "run.scheduler=sync",
    "render.resolution=[128, 128]",
    "render.spp=[4]",
    "render.reference_spp=32",
    "corpus.n_scenes=6",
    "tile.patch_size=64",
    "tile.crops_per_scene=4",
    "tile.split=[0.5, 0.5, 0.0]",
]


def step_seconds(metrics_csv: Path, step: int, patches_per_step: int) -> float:
    """Seconds per global step over the logging window that ends at `step` (patches_per_s counts every
    batch of every branch)."""
    with metrics_csv.open() as f:
        rate = next(
            float(r["value"]) for r in csv.DictReader(f) if r["tag"] == "patches_per_s" and int(r["step"]) == step
        )
    return patches_per_step / rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", action="append", default=[], dest="overrides", help="section.key=value")
    parser.add_argument("--nproc", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--batch", type=int, default=4, help="global batch (train.batch_size)")
    parser.add_argument("--window", type=int, default=10, help="steps per timed window")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--precision", default="float32")
    parser.add_argument("--threads", type=int, default=1, help="CPU threads per process (train.threads)")
    args = parser.parse_args()
    use_variant("auto")
    device = resolve_device(args.device)
    with tempfile.TemporaryDirectory(prefix="admc-bench-ddp-") as tmp:
        cfg = load_config(None, [*STORE, *args.overrides, f"run.workdir='{tmp}'"])
        store = build_dataset(cfg, progress=False).store
        settings = dataclasses.replace(
            cfg.train,
            steps=2 * args.window,
            batch_size=args.batch,
            val_every=0,
            log_every=args.window,
            checkpoint_every=2 * args.window,
            threads=args.threads,
            device=args.device,
            precision=args.precision,
            l1_warmup_steps=0,
            critic_only_steps=0,
            head_tail_start_step=0,
        )
        print(
            f"{device.type}, {args.precision}, global batch {args.batch} of {cfg.tile.patch_size}px patches, "
            f"model channels={cfg.model.channels} blocks={cfg.model.blocks}, adversarial steps "
            f"(critic + generator, both branches), {args.threads} CPU thread(s) per process"
        )
        base = None
        for nproc in args.nproc:
            out = Path(tmp) / f"run{nproc}"
            kwargs = dict(store_path=store, out_dir=out, settings=settings, model=cfg.model, progress=False)
            result = distributed.launch(nproc, device, train, kwargs)
            per_step = args.batch * settings.critic_steps_per_g * len(result.branches)
            seconds = step_seconds(out / "metrics.csv", 2 * args.window, per_step)
            base = base or seconds
            print(
                f"{nproc} process(es): {seconds * 1000:.0f} ms per global step, "
                f"x{base / seconds:.2f} vs {args.nproc[0]} ({', '.join(result.branches)})"
            )


if __name__ == "__main__":
    main()
