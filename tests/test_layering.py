"""Imports flow one way (docs/architecture.md): cli -> pipeline -> model -> stores -> admc/common and
admc/errors.py, and inside pipeline/ and model/ from the upper layers to the lower ones. Read from the
source, imports inside functions included: a lazy import upward is still a layer upside down."""

import ast
import tomllib
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

LAYERS = [  # (module prefix, layer): the longest matching prefix decides; higher layers may import lower ones
    ("admc", 0),
    ("admc.common", 0),
    ("admc.errors", 0),
    ("admc.stores", 1),
    ("admc.model", 2),
    ("admc.model.nets", 3),
    ("admc.model.training", 4),
    ("admc.model.inference", 4),
    ("admc.pipeline", 5),
    ("admc.pipeline.scene_names", 5),
    ("admc.pipeline.config", 6),
    ("admc.pipeline.engine", 7),
    ("admc.pipeline.render", 8),
    ("admc.pipeline.tiler", 9),
    ("admc.pipeline.evaluation", 9),
    ("admc.pipeline.weights", 9),
    ("admc.pipeline.stages", 10),
    ("admc.cli", 11),
]
APART = [("admc.model.training", "admc.model.inference")]
"""Layers side by side that never import each other (inference runs without the training stack)."""


def layer_of(module: str) -> tuple[str, int]:
    prefix, layer = max(
        ((p, n) for p, n in LAYERS if module == p or module.startswith(p + ".")), key=lambda item: len(item[0])
    )
    return prefix, layer


def package_modules() -> dict[str, Path]:
    """Every module of the package, by its import name (pyproject's folder mapping)."""
    folders = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    modules = {}
    for package, folder in folders.items():
        for path in (REPO / folder).rglob("*.py"):
            parts = list(path.relative_to(REPO / folder).with_suffix("").parts)
            modules[".".join([package, *parts[:-1]] + ([] if parts[-1] == "__init__" else parts[-1:]))] = path
    return modules


def imported(module: str, path: Path) -> set[str]:
    """The admc modules `module` imports anywhere in its source, relative imports resolved."""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = (
                ".".join(package[: len(package) - node.level + 1] + [node.module or ""]).strip(".")
                if node.level
                else node.module
            )
            names.add(base)
            names |= {f"{base}.{alias.name}" for alias in node.names}  # `from pkg import module`
    return {name for name in names if name == "admc" or name.startswith("admc.")}


def test_imports_go_down_the_layers():
    modules = package_modules()
    upward = []
    for module, path in sorted(modules.items()):
        own_prefix, own = layer_of(module)
        for name in sorted(imported(module, path) & set(modules)):  # `from pkg import function`: pkg counts
            prefix, layer = layer_of(name)
            side_by_side = {own_prefix, prefix} in [set(pair) for pair in APART]
            if (layer > own and prefix != own_prefix) or side_by_side:
                upward.append(f"{module} ({own_prefix}) imports {name} ({prefix})")
    assert len(modules) > 100 and not upward, "\n".join(upward)


def test_no_two_modules_share_a_name():
    """A module's name says where it is: two `evaluate.py` (or `export.py`, `settings.py`) doing different jobs
    in different folders make a reader open the wrong one. (A command's module in stages/ may share its name
    with the package of its parts: stages/render.py runs render/.)"""
    modules = [module for module, path in package_modules().items() if path.name not in ("__init__.py", "__main__.py")]
    names = Counter(module.rsplit(".", 1)[1] for module in modules)
    assert [name for name, count in names.items() if count > 1] == []
