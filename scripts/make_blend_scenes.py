"""Write seeded procedural Blender scenes (.blend), a Cycles domain for `corpus.blend_dirs`: interiors and
product shots built from Blender's primitives and procedural textures (no downloaded asset). Runs Blender
(`bash scripts/setup.sh --blender`, or render.blender / ADMC_BLENDER) on pipeline/render/blender/build_scenes.py.

    python scripts/make_blend_scenes.py /tmp/cycles --scenes 12 [--seed 0] [--resolution 256 256]

The same --seed writes the same scenes (scenes.json beside them lists what the seed decided: each object, its
place, its colour); each file's own resolution is --resolution (what `corpus.xml_resolution = "film"`
renders at).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from admc.errors import AdmcError
from admc.pipeline.render.blender.locate import require_blender

BUILDER = Path(__file__).resolve().parents[1] / "pipeline" / "render" / "blender" / "build_scenes.py"


def make_scenes(
    out_dir: Path, scenes: int, seed: int = 0, resolution: tuple[int, int] = (256, 256), blender: str = ""
) -> list[Path]:
    """Write the scenes into out_dir (created); returns their paths."""
    command = require_blender(blender, "scripts/make_blend_scenes.py")
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="admc-blend-build-") as folder:
        job = Path(folder) / "job.json"
        job.write_text(json.dumps({"out_dir": folder, "scenes": scenes, "seed": seed, "resolution": list(resolution)}))
        out = subprocess.run(
            [*command, str(BUILDER), "--", str(job)], capture_output=True, text=True, stdin=subprocess.DEVNULL
        )
        done = Path(folder) / "done.json"
        if out.returncode != 0 or not done.is_file():
            raise AdmcError(f"scripts/make_blend_scenes.py: Blender failed: {out.stderr.strip()[-2000:]}")
        report = json.loads(done.read_text())
        written = []
        for path in map(Path, report["written"]):
            target = out_dir / path.name
            shutil.move(path, target)
            written.append(target)
    (out_dir / "scenes.json").write_text(json.dumps(report["scenes"], indent=1))
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--scenes", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", type=int, nargs=2, default=(256, 256), metavar=("WIDTH", "HEIGHT"))
    parser.add_argument(
        "--blender", default="", help="a Blender executable or a Python with bpy (default: as render.blender finds it)"
    )
    args = parser.parse_args()
    if args.scenes < 1 or min(args.resolution) < 1:
        parser.error("--scenes and --resolution must be positive")
    try:
        written = make_scenes(args.out_dir, args.scenes, args.seed, tuple(args.resolution), args.blender)
    except AdmcError as exc:
        sys.exit(f"error: {exc}")
    print(f"wrote {len(written)} scenes to {args.out_dir}: {', '.join(p.name for p in written)}")


if __name__ == "__main__":
    main()
