"""A plain (non-editable) install carries the shipped weights: the wheel lists them, and the installed
package's weights finder returns them, so `admc-pipe denoise` works from any install."""

import json
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _source_copy(dest: Path) -> Path:
    """What the wheel is built from (pyproject's package folders), copied so the build leaves no
    build/ or egg-info in the checkout."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    folders = set(pyproject["tool"]["setuptools"]["package-dir"].values())
    for folder in folders:
        shutil.copytree(REPO / folder, dest / folder, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(REPO / name, dest / name)
    return dest


def _package_files(source: Path) -> set[str]:
    """Every file of the package folders of `source` (modules and package data), as the wheel names it."""
    folders = tomllib.loads((source / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    return {
        f"{package.replace('.', '/')}/{path.relative_to(source / folder).as_posix()}"
        for package, folder in folders.items()
        for path in (source / folder).rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }


@pytest.mark.slow
def test_a_wheel_ships_the_weights_and_its_install_finds_them(tmp_path):
    source = _source_copy(tmp_path / "src")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--wheel-dir",
            str(tmp_path / "dist"),
            str(source),
        ],
        check=True,
        capture_output=True,
    )
    (wheel,) = (tmp_path / "dist").glob("admc-*.whl")
    shipped = [entry["file"] for entry in json.loads((REPO / "weights" / "manifest.json").read_text())["weights"]]
    listed = set(zipfile.ZipFile(wheel).namelist())
    assert {f"admc/weights/{name}" for name in ["manifest.json", *shipped]} <= listed
    # every module (the packages are found by setup.py, not listed by hand) and every data file: configs,
    # weights, the report's templates
    assert _package_files(source) - listed == set()
    assert {
        "admc/configs/default.toml",
        "admc/pipeline/evaluation/templates/report.html",
        "admc/pipeline/render/scenes/families.py",
    } <= listed

    site = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--target", str(site), str(wheel)],
        check=True,
        capture_output=True,
    )
    # The installed copy comes first on the path (before this checkout's editable install); its
    # dependencies (torch, ...) still come from this environment.
    probe = (
        "import admc; from admc.pipeline.config import load_config; "
        "from admc.pipeline.weights import WEIGHTS_DIR, shipped_weights; "
        "print(admc.__file__); print(WEIGHTS_DIR); print(shipped_weights(load_config().model))"
    )
    env = {**os.environ, "PYTHONPATH": str(site)}
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, env=env, check=True, capture_output=True, text=True
    ).stdout.split("\n")
    package, weights_dir, default = (Path(line) for line in out[:3])
    assert package.is_relative_to(site) and weights_dir == site / "admc" / "weights"
    assert default == weights_dir / "admc-small-pretrained.pt" and default.is_file()
