#!/usr/bin/env python3
"""Write a fine-tuning domain: a folder of Mitsuba 3 XML frames, one file per frame, that admc's
procedural pretraining families (room, tabletop, studio) never draw.

    python scripts/make_domain_scenes.py OUT_DIR --domain interior --frames 32 --seed 0

Domains (scripts/domains/):
  interior  one furnished living room seen from many cameras, by day (sun and sky through a window),
            at dusk (sky and downlights) and at night (downlights and a floor lamp)
  product   a product shot on a turntable (glass bottle, glazed mug, wooden box, metal tin) turned through
            a revolution, three camera heights, three softbox setups
  exterior  a brick house on a lawn with trees, a fence and a car, under sun and sky at four times of day,
            from eye level and from a drone
  cbox      Cornell-box-like interiors, each frame a different box (the other three are one set each)

A domain's frames share one set (its geometry, materials and texture files, drawn from --seed), so a
split by frame into train / val / test is what a studio has: its own set, new cameras and lights.
Textures and meshes are written beside the XML files as EXR and OBJ. The same seed writes the same
files on any machine; another seed, another set.
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from domains import cbox, exterior, interior, product  # noqa: E402

DOMAINS = {"interior": interior, "product": product, "exterior": exterior, "cbox": cbox}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out_dir", type=Path, help="folder to write the frames into (created if missing)")
    parser.add_argument("--domain", choices=sorted(DOMAINS), default="cbox", help="which domain (default cbox)")
    parser.add_argument(
        "--frames", "--scenes", type=int, default=24, dest="frames", help="how many frames (default 24)"
    )
    parser.add_argument("--seed", type=int, default=0, help="the same seed writes the same set (default 0)")
    args = parser.parse_args()
    if args.frames < 1:
        parser.error(f"--frames must be at least 1, got {args.frames}")
    if args.seed < 0:
        parser.error(f"--seed must be non-negative, got {args.seed}")
    if args.out_dir.exists() and not args.out_dir.is_dir():
        parser.error(f"{args.out_dir} exists and is not a folder")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    paths = DOMAINS[args.domain].write(args.out_dir, args.seed, args.frames)
    print(f"wrote {len(paths)} {args.domain} frames (seed {args.seed}) to {args.out_dir}")


if __name__ == "__main__":
    main()
