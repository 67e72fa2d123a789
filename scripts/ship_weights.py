#!/usr/bin/env python3
"""Publish a training run's fp16 weights in weights/ with a manifest entry saying how they were made.

    python scripts/ship_weights.py RUN_DIR NAME --note "how it was trained"
    python scripts/ship_weights.py RUN_DIR NAME --checkpoint SAVED.pt --note "..."

The first form ships the run's weights-fp16.pt (each branch's best step by the run's own validation).
The second ships a checkpoint of that run saved at a chosen step (its moving average, as the run would
ship it), for weights selected on something the run did not validate on (e.g. the out-of-family set).
With `--blend-from WEIGHTS --blend A` it ships (1 - A) x WEIGHTS + A x the checkpoint, tensor by tensor
(weight-space ensembling, WiSE-FT: Wortsman et al. 2022): a fine-tune blended with the weights it started
from keeps more of what those did well than either end (docs/results/2026-12-03-broad-finetune-blend.md).
The manifest is what `admc-pipe train --stage finetune` (and denoise/eval without --weights) search for
weights matching the configured [model]; an entry for the same architecture is replaced.
"""

import argparse
import csv
import hashlib
import json
import shutil
from pathlib import Path

from admc.model.nets.settings import ModelSettings
from admc.pipeline.weights import WEIGHTS_DIR
from admc.stores.checkpoints import export_weights, load_checkpoint, load_weights, read_networks


def shipped_validation(run: Path, selected: dict) -> dict:
    """Each branch's validation values at the step its shipped networks come from (the last step's for
    weights that record no selection)."""
    values: dict[str, float] = {}
    with open(run / "metrics.csv") as f:
        for row in csv.DictReader(f):
            branch = row["tag"].split("/")[0]
            if "/val_" in row["tag"] and (branch not in selected or int(row["step"]) == selected[branch]["step"]):
                values[row["tag"]] = round(float(row["value"]), 5)
    return values


def blended(start: dict, end: dict, share: float) -> dict:
    """{branch: {net: state}}: (1 - share) x start + share x end for every float tensor (others from end)."""
    return {
        branch: {
            net: {
                key: (1 - share) * start[branch][net][key].float() + share * value.float()
                if value.is_floating_point()
                else value
                for key, value in state.items()
            }
            for net, state in nets.items()
        }
        for branch, nets in end.items()
    }


def export_checkpoint(
    path: Path, target: Path, blend_from: Path | None = None, share: float = 1.0
) -> tuple[dict, dict]:
    """Write `path`'s networks (moving average where the run kept one), blended with `blend_from`'s if
    given, as fp16 weights at `target`; (its checkpoint, the selection it records)."""
    checkpoint = load_checkpoint(path)
    nets, model, transform = read_networks(path)
    chosen = {"step": checkpoint["step"], "chosen_by": "ship_weights --checkpoint"}
    if blend_from is not None:
        start, start_model, _ = read_networks(blend_from)
        if ModelSettings.from_saved(start_model) != ModelSettings.from_saved(model) or set(start) != set(nets):
            raise SystemExit(f"{blend_from}: not the architecture and branches of {path}: cannot blend them")
        nets = blended(start, nets, share)
        chosen.update(blend_from=str(blend_from), blend=share)
    selected = {branch: dict(chosen) for branch in nets}
    export_weights(
        target,
        nets,
        {
            "model": model,
            "transform": transform,
            "patch_size": checkpoint["store"]["patch_size"],
            "stage": checkpoint["stage"],
            "step": checkpoint["step"],
            "selected": selected,
            "store_fingerprint": checkpoint["store"]["fingerprint"],
            "precision": checkpoint["precision"],
        },
    )
    return checkpoint, selected


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("name")
    parser.add_argument("--checkpoint", type=Path, help="a checkpoint of RUN saved at the step to ship")
    parser.add_argument("--blend-from", type=Path, help="weights to blend the checkpoint with (its start)")
    parser.add_argument("--blend", type=float, default=0.5, help="the checkpoint's share of the blend")
    parser.add_argument("--note", default="")
    parser.add_argument("--to", type=Path, default=WEIGHTS_DIR, help="the weights folder (default: the package's)")
    args = parser.parse_args()
    if args.blend_from and not args.checkpoint:
        parser.error("--blend-from needs --checkpoint")
    if not 0.0 <= args.blend <= 1.0:
        parser.error(f"--blend {args.blend}: the checkpoint's share, from 0 to 1")
    target = args.to / f"{args.name}.pt"
    args.to.mkdir(exist_ok=True)
    if args.checkpoint:
        checkpoint, selected = export_checkpoint(args.checkpoint, target, args.blend_from, args.blend)
        model = checkpoint["model"]
    else:
        weights = load_weights(args.run / "weights-fp16.pt")
        checkpoint = load_checkpoint(args.run / "checkpoint.pt")
        shutil.copyfile(args.run / "weights-fp16.pt", target)
        model, selected = weights["metadata"]["model"], weights["metadata"].get("selected", {})
    entry = {
        "file": target.name,
        "model": model,
        "stage": checkpoint["stage"],
        "steps": checkpoint["step"],
        "settings": checkpoint["settings"],
        "selected": selected,
        "validation": {} if args.blend_from else shipped_validation(args.run, selected),
        "note": args.note,
        "sha256": hashlib.sha256(target.read_bytes()).hexdigest(),
        "bytes": target.stat().st_size,
    }
    manifest_path = args.to / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {"weights": []}
    same = ModelSettings.from_saved(entry["model"])  # one shipped file per architecture: replace its entry
    manifest["weights"] = [e for e in manifest["weights"] if ModelSettings.from_saved(e["model"]) != same] + [entry]
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"{target} ({entry['bytes'] / 2**20:.2f} MiB), manifest: {manifest_path}")


if __name__ == "__main__":
    main()
