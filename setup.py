"""The package list of admc, found rather than typed: each folder of pyproject's
[tool.setuptools.package-dir] is one part of the import package `admc` (pipeline/ is admc.pipeline, ...), and
every folder with an __init__.py below it is a subpackage. Everything else (metadata, dependencies, package
data) is in pyproject.toml."""

import tomllib
from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).resolve().parent
PARTS = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]["package-dir"]


def packages() -> list[str]:
    """Each part's package and every package found under its folder, prefixed with the part's name."""
    return [
        name
        for part, folder in PARTS.items()
        for name in [part, *(f"{part}.{sub}" for sub in find_packages(str(ROOT / folder)))]
    ]


setup(packages=packages())
