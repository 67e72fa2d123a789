#!/usr/bin/env python3
"""Write weights of a slimmer generator (model.cfm_per_block = 1, model.condition_layers = 1) fitted to
trained weights of the paper's layout on a patch store's train patches (model/training/slimming.py).

    python scripts/slim_weights.py WEIGHTS STORE OUT [--cfm-per-block 1] [--condition-layers 1] [--patches 48]

The result is a fine-tuning start, not weights to ship: fitted on patches, it can be far off on whole
images. Fine-tune it with the full weights as teacher:
`admc-pipe train --stage finetune --init OUT --set model.cfm_per_block=1 --set model.condition_layers=1
--set train.distill_from=WEIGHTS ...` (docs/results/2026-12-03-slim-generator.md).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import admc  # noqa: F401  (first: it sets GOMP_SPINCOUNT before torch loads, as in admc-pipe)
import numpy as np
import torch
from torch import Tensor

from admc.common.layout import BASE_QUALITIES
from admc.errors import AdmcError
from admc.model.nets.backbones import build_generator
from admc.model.nets.settings import ModelSettings
from admc.model.training.slimming import slim_generator
from admc.stores.checkpoints import export_weights, load_weights
from admc.stores.patches import PatchReader


def read_batch(
    store: Path, branch: str, model: ModelSettings, transform: dict, patches: int, seed: int
) -> dict[str, Tensor]:
    reader = PatchReader(
        store,
        "train",
        expect_transform=transform,
        branch=branch,
        base=model.base if model.base in BASE_QUALITIES else None,
        noise=model.noise_input,
    )
    rows = np.random.default_rng(seed).choice(len(reader), size=min(patches, len(reader)), replace=False)
    items = [reader[int(row)] for row in rows]
    return {
        key: torch.from_numpy(np.stack([item[key] for item in items]))
        for key in ("noisy", "features", "base")
        if key in items[0]
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("weights", type=Path, help="fp16 weights of the full generator (e.g. weights/*.pt)")
    parser.add_argument("store", type=Path, help="a patch store (patches.zarr) whose train split to fit on")
    parser.add_argument("out", type=Path, help="where to write the slim weights (a fine-tuning start)")
    parser.add_argument("--cfm-per-block", type=int, default=1, choices=(1, 2))
    parser.add_argument("--condition-layers", type=int, default=1, choices=(1, 2))
    parser.add_argument("--patches", type=int, default=48, help="train patches per branch to fit on")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    try:
        slim_weights(args)
    except AdmcError as exc:  # a missing or malformed weights file or store: one line, no traceback
        raise SystemExit(f"slim_weights: {exc}") from None


def slim_weights(args: argparse.Namespace) -> None:
    saved = load_weights(args.weights)
    metadata = saved["metadata"]
    model = ModelSettings.from_saved(metadata["model"])
    if model.backbone != "residual":
        raise SystemExit(f"{args.weights}: model.backbone {model.backbone!r}; only the residual body is slimmed here")
    slim_model = dataclasses.replace(model, cfm_per_block=args.cfm_per_block, condition_layers=args.condition_layers)
    if (
        args.cfm_per_block > model.cfm_per_block
        or args.condition_layers > model.condition_layers
        or slim_model == model
    ):
        raise SystemExit(
            f"{args.weights}: has cfm_per_block {model.cfm_per_block} and condition_layers "
            f"{model.condition_layers}; asked for {args.cfm_per_block} and {args.condition_layers}, "
            "which is not slimmer"
        )
    branches = {}
    for branch, nets in saved["branches"].items():
        full = build_generator(model).eval()
        full.load_state_dict({k: v.float() for k, v in nets["generator"].items()})
        slim = build_generator(slim_model).eval()
        batch = read_batch(args.store, branch, model, metadata["transform"], args.patches, args.seed)
        slim_generator(full, slim, batch, args.seed)
        with torch.no_grad():
            inputs = (batch["noisy"], batch["features"], batch.get("base"))
            full_out, slim_out = full(*inputs), slim(*inputs)
        gap = (slim_out - full_out).abs().mean().item() / full_out.abs().mean().item()
        print(
            f"{branch}: slim output differs from the full one by {gap:.4f} of its mean (log domain, "
            f"{len(batch['noisy'])} fitting patches)"
        )
        branches[branch] = {"generator": slim.state_dict(), "critic": nets["critic"]}
    provenance = (
        f"slimmed from {args.weights} by scripts/slim_weights.py on {args.store} (train split, "
        f"{args.patches} patches per branch, seed {args.seed})"
    )
    export_weights(args.out, branches, {**metadata, "model": dataclasses.asdict(slim_model), "provenance": provenance})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
