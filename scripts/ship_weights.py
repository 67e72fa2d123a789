#!/usr/bin/env python3
"""Publish a training run's fp16 weights in weights/ with a manifest entry saying how they were made.

    python scripts/ship_weights.py RUN_DIR NAME --note "how it was trained"

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
from admc.stores.checkpoints import load_checkpoint, load_weights


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("name")
    parser.add_argument("--note", default="")
    args = parser.parse_args()
    weights = load_weights(args.run / "weights-fp16.pt")
    checkpoint = load_checkpoint(args.run / "checkpoint.pt")
    target = WEIGHTS_DIR / f"{args.name}.pt"
    WEIGHTS_DIR.mkdir(exist_ok=True)
    shutil.copyfile(args.run / "weights-fp16.pt", target)
    entry = {"file": target.name, "model": weights["metadata"]["model"], "stage": checkpoint["stage"],
             "steps": checkpoint["step"], "settings": checkpoint["settings"],
             "selected": weights["metadata"].get("selected", {}),
             "validation": shipped_validation(args.run, weights["metadata"].get("selected", {})), "note": args.note,
             "sha256": hashlib.sha256(target.read_bytes()).hexdigest(), "bytes": target.stat().st_size}
    manifest_path = WEIGHTS_DIR / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {"weights": []}
    same = ModelSettings.from_saved(entry["model"])  # one shipped file per architecture: replace its entry
    manifest["weights"] = [e for e in manifest["weights"] if ModelSettings.from_saved(e["model"]) != same] + [entry]
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"{target} ({entry['bytes'] / 2**20:.2f} MiB), manifest: {manifest_path}")


if __name__ == "__main__":
    main()
