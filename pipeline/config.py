"""Typed, validated run configuration.

`configs/default.toml` holds every value; a user config overlays it and `--set section.key=value`
overrides overlay both. The dataclasses below are the schema: an unknown key, a value of the wrong
type or out of range is a ConfigError that names the key, so a typo never silently runs the defaults.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import tomllib
import typing
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from admc.common.layout import BASE_QUALITIES, ENGINE_CHOICES, ENSEMBLES
from admc.common.oidn import QUALITIES as OIDN_QUALITIES
from admc.errors import ConfigError, SettingError
from admc.model.checks import require
from admc.model.nets.settings import DOWNSAMPLING, ModelSettings
from admc.pipeline.scene_names import CONSTRUCT_NAMES, FAMILY_NAMES, OOD_CONSTRUCT_NAMES
from admc.model.train_settings import TrainSettings


MAX_RESOLUTION = 16384
"""Largest render side: a 16K film already takes GBs per buffer; far larger ones fail deep in Dr.Jit."""
SPLIT_TOLERANCE = 1e-6
"""How far tile.split's fractions may sum from 1 (decimal fractions such as 0.8 + 0.1 + 0.1 are inexact)."""


@dataclass(frozen=True)
class CorpusConfig:
    families: tuple[str, ...]
    n_scenes: int
    seed: int
    constructs: tuple[str, ...]
    construct_chance: float
    held_out_families: tuple[str, ...]
    xml_dirs: tuple[str, ...]
    xml_resolution: str
    blend_dirs: tuple[str, ...]

    def check(self) -> None:
        require(self.n_scenes >= 0, "n_scenes", f"must be >= 0, got {self.n_scenes}")
        for key, names, known in (
            ("families", self.families, FAMILY_NAMES),
            ("held_out_families", self.held_out_families, FAMILY_NAMES),
        ):
            unknown = [name for name in names if name not in known]
            require(not unknown, key, f"unknown families {unknown}; known: {', '.join(sorted(known))}")
        held = [name for name in self.families if name in self.held_out_families]
        require(
            not held,
            "families",
            f"{held} held out of training (corpus.held_out_families); "
            "they are the out-of-family set's, never tiled into training",
        )
        ood = [name for name in self.constructs if name in OOD_CONSTRUCT_NAMES]
        require(not ood, "constructs", f"{ood} are held out for the out-of-family set (family 'ood')")
        unknown = [name for name in self.constructs if name not in CONSTRUCT_NAMES]
        require(not unknown, "constructs", f"unknown constructs {unknown}; known: {', '.join(CONSTRUCT_NAMES)}")
        require(
            0.0 <= self.construct_chance <= 1.0, "construct_chance", f"must be in [0, 1], got {self.construct_chance}"
        )
        require(
            self.xml_resolution in ("render", "film"),
            "xml_resolution",
            f"must be render or film, got {self.xml_resolution!r}",
        )
        require(self.n_scenes == 0 or len(self.families) > 0, "families", "empty but n_scenes > 0")


@dataclass(frozen=True)
class RenderConfig:
    variant: str
    resolution: tuple[int, int]
    spp: tuple[int, ...]
    reference_spp: int
    val_reference_spp: int
    max_depth: int
    seed: int
    max_spp_per_pass: int
    blender: str
    cycles_subrenders: int
    blender_threads: int

    def check(self) -> None:
        w, h = self.resolution
        require(
            1 <= w <= MAX_RESOLUTION and 1 <= h <= MAX_RESOLUTION,
            "resolution",
            f"width and height must be in 1..{MAX_RESOLUTION}, got {list(self.resolution)}",
        )
        require(len(self.spp) > 0, "spp", "needs at least one sample count")
        require(all(s >= 1 for s in self.spp), "spp", f"every spp must be >= 1, got {list(self.spp)}")
        require(len(set(self.spp)) == len(self.spp), "spp", f"duplicates in {list(self.spp)}")
        require(
            self.reference_spp > max(self.spp),
            "reference_spp",
            f"must exceed every input spp (max {max(self.spp)}), got {self.reference_spp}",
        )
        require(
            self.val_reference_spp == 0 or self.val_reference_spp > max(self.spp),
            "val_reference_spp",
            f"must be 0 (reference_spp) or exceed every input spp (max {max(self.spp)}), got {self.val_reference_spp}",
        )
        require(1 <= self.max_depth <= 64, "max_depth", f"must be in 1..64, got {self.max_depth}")
        require(self.max_spp_per_pass >= 1, "max_spp_per_pass", "must be >= 1")
        require(
            1 <= self.cycles_subrenders <= 64, "cycles_subrenders", f"must be in 1..64, got {self.cycles_subrenders}"
        )
        require(self.blender_threads >= 0, "blender_threads", f"must be >= 0, got {self.blender_threads}")


@dataclass(frozen=True)
class TileConfig:
    store: str
    patch_size: int
    crops_per_scene: int
    candidates_per_crop: int
    split: tuple[float, float, float]
    split_exact: bool
    seed: int
    val_set: str
    oidn_base: bool
    refiner_base: str
    noise_maps: bool
    clean_targets: bool

    def check(self) -> None:
        # [model]'s critic takes the patch through 5 stride-2 stages: checked here, before a store is built
        require(
            self.patch_size >= DOWNSAMPLING and self.patch_size % DOWNSAMPLING == 0,
            "patch_size",
            f"must be a multiple of {DOWNSAMPLING} (the critic halves it 5 times), got {self.patch_size}",
        )
        require(self.crops_per_scene >= 1, "crops_per_scene", "must be >= 1")
        require(self.candidates_per_crop >= 1, "candidates_per_crop", "must be >= 1")
        require(
            all(f >= 0 for f in self.split) and abs(sum(self.split) - 1) <= SPLIT_TOLERANCE,
            "split",
            f"the train, val and test fractions must be >= 0 and sum to 1, got {list(self.split)} "
            f"(sum {sum(self.split):g})",
        )
        require(bool(self.store), "store", "must not be empty")
        require(self.val_set in ("split", "ood"), "val_set", f"must be split or ood, got {self.val_set!r}")
        require(
            self.refiner_base in BASE_QUALITIES,
            "refiner_base",
            f"must be one of {', '.join(BASE_QUALITIES)}, got {self.refiner_base!r}",
        )


@dataclass(frozen=True)
class EvalConfig:
    split: str
    out_dir: str
    oidn_quality: str
    oidn_prefiltered: bool
    optix: str
    repeats: int
    warmup: int
    test_families: tuple[str, ...]
    test_scenes_per_family: int
    test_seed: int
    test_resolution: tuple[int, int]
    ood_families: tuple[str, ...]
    ood_scenes_per_family: int
    ood_seed: int
    ensemble: int
    dark_pass: bool
    engine: str
    also_ensemble_dark: bool
    keep_resolved: bool
    reference_spp: int

    def check(self) -> None:
        require(
            self.test_scenes_per_family >= 0,
            "test_scenes_per_family",
            f"must be >= 0, got {self.test_scenes_per_family}",
        )
        require(
            self.test_scenes_per_family == 0 or len(self.test_families) > 0,
            "test_families",
            "empty but eval.test_scenes_per_family > 0",
        )
        w, h = self.test_resolution
        require(
            1 <= w <= MAX_RESOLUTION and 1 <= h <= MAX_RESOLUTION,
            "test_resolution",
            f"width and height must be in 1..{MAX_RESOLUTION}, got {list(self.test_resolution)}",
        )
        require(
            self.split in ("train", "val", "test", "ood"),
            "split",
            f"must be train, val, test or ood, got {self.split!r}",
        )
        require(
            self.ood_scenes_per_family >= 0, "ood_scenes_per_family", f"must be >= 0, got {self.ood_scenes_per_family}"
        )
        require(
            self.split != "ood" or (self.ood_scenes_per_family > 0 and self.ood_families),
            "ood_families",
            "eval.split = 'ood' needs ood_families and ood_scenes_per_family > 0",
        )
        unknown = [name for name in self.ood_families if name not in FAMILY_NAMES]
        require(not unknown, "ood_families", f"unknown families {unknown}; known: {', '.join(sorted(FAMILY_NAMES))}")
        require(
            self.oidn_quality in OIDN_QUALITIES,
            "oidn_quality",
            f"must be one of {', '.join(OIDN_QUALITIES)}, got {self.oidn_quality!r}",
        )
        require(
            isinstance(self.oidn_prefiltered, bool),
            "oidn_prefiltered",
            f"must be true or false, got {self.oidn_prefiltered!r}",
        )
        require(self.optix in ("auto", "on", "off"), "optix", f"must be auto, on or off, got {self.optix!r}")
        require(self.repeats >= 1, "repeats", "must be >= 1")
        require(self.warmup >= 0, "warmup", "must be >= 0")
        require(self.ensemble in ENSEMBLES, "ensemble", f"must be one of {ENSEMBLES}, got {self.ensemble!r}")
        require(
            self.engine in ENGINE_CHOICES, "engine", f"must be one of {', '.join(ENGINE_CHOICES)}, got {self.engine!r}"
        )


@dataclass(frozen=True)
class RunConfig:
    workdir: str
    scheduler: str
    workers: int

    def check(self) -> None:
        require(self.workers >= 0, "workers", f"must be >= 0 (0 = auto), got {self.workers}")
        require(bool(self.scheduler), "scheduler", "must not be empty")
        require(bool(self.workdir), "workdir", "must not be empty")
        require(
            not Path(self.workdir).exists() or Path(self.workdir).is_dir(),
            "workdir",
            f"{self.workdir} is a file; it must name a folder (made if missing)",
        )


WALLTIME = re.compile(r"^(\d+-)?\d+:\d{2}:\d{2}$")


@dataclass(frozen=True)
class ClusterConfig:
    """The SLURM jobs `run.scheduler = "slurm"` submits (pipeline/engine/slurm.py): one dask worker per job."""

    jobs: int
    cores: int
    memory: str
    gpus: int
    walltime: str
    queue: str
    account: str
    interface: str
    job_directives: tuple[str, ...]

    def check(self) -> None:
        from dask.utils import parse_bytes

        require(self.jobs >= 1, "jobs", f"must be >= 1, got {self.jobs}")
        require(self.cores >= 1, "cores", f"must be >= 1, got {self.cores}")
        require(self.gpus >= 0, "gpus", f"must be >= 0, got {self.gpus}")
        try:
            parse_bytes(self.memory)
        except (ValueError, TypeError):
            require(False, "memory", f"must be a size such as '32GB' or '64GiB', got {self.memory!r}")
        require(
            bool(WALLTIME.match(self.walltime)), "walltime", f"must be HH:MM:SS or D-HH:MM:SS, got {self.walltime!r}"
        )
        for i, line in enumerate(self.job_directives):
            require(
                line.startswith("-") and "\n" not in line,
                f"job_directives[{i}]",
                f"must be one sbatch option such as '--constraint=a100', got {line!r}",
            )


@dataclass(frozen=True)
class Config:
    corpus: CorpusConfig
    render: RenderConfig
    tile: TileConfig
    model: ModelSettings
    train: TrainSettings
    eval: EvalConfig
    run: RunConfig
    cluster: ClusterConfig

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def workdir_path(self, relative: str) -> Path:
        """A path from the config: absolute as given, else under run.workdir."""
        path = Path(relative)
        return path if path.is_absolute() else Path(self.run.workdir) / path


def _coerce(value, annotation, key: str):
    """Check a TOML value against a field's type; TOML arrays become tuples."""
    origin = typing.get_origin(annotation)
    if origin is tuple:
        args = typing.get_args(annotation)
        require(isinstance(value, (list, tuple)), key, f"expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        require(len(value) == len(args), key, f"expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if annotation is float:
        require(
            isinstance(value, (int, float)) and not isinstance(value, bool), key, f"expected a number, got {value!r}"
        )
        require(math.isfinite(value), key, f"must be a finite number, got {value!r}")
        return float(value)
    require(
        isinstance(value, annotation) and not (annotation is int and isinstance(value, bool)),
        key,
        f"expected {annotation.__name__}, got {value!r}",
    )
    return value


def _merge(base: dict, overlay: dict, source: str) -> dict:
    merged = {section: dict(values) for section, values in base.items()}
    for section, values in overlay.items():
        if section not in merged:
            raise ConfigError(f"unknown config section '{section}' in {source}; known: {', '.join(merged)}")
        if not isinstance(values, dict):
            raise ConfigError(f"config key '{section}' in {source}: expected a [{section}] table")
        for key, value in values.items():
            if key not in merged[section]:
                raise ConfigError(
                    f"unknown config key '{section}.{key}' in {source}; known: {', '.join(merged[section])}"
                )
            merged[section][key] = value
    return merged


def _parse_override(item: str) -> tuple[str, str, object]:
    if "=" not in item:
        raise ConfigError(f"override {item!r} must look like section.key=value")
    dotted, raw = item.split("=", 1)
    if dotted.count(".") != 1:
        raise ConfigError(f"override {item!r}: key must be section.key")
    section, key = dotted.strip().split(".")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # a bare string such as a scheduler address
    return section, key, value


def _read_toml(path: Path) -> dict:
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except IsADirectoryError:
        raise ConfigError(f"config file {path} is a directory; --config names a .toml file") from None
    except OSError as exc:
        raise ConfigError(f"config file {path} cannot be read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"config file {path} is not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset "
            f"{exc.start}); TOML files are UTF-8"
        ) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None


def _toml_value(value) -> str:
    """One value in TOML syntax: JSON's string escapes are valid TOML basic strings."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")  # TOML also escapes DEL
    return repr(value)  # int, or float (repr is exact; inf and nan are TOML's spelling too)


def config_toml(cfg: Config) -> str:
    """The resolved config as TOML that load_config reads back to the same Config."""
    lines = []
    for section, values in cfg.to_dict().items():
        lines += ([""] if lines else []) + [f"[{section}]"]
        lines += [f"{key} = {_toml_value(value)}" for key, value in values.items()]
    return "\n".join(lines) + "\n"


def default_config_text() -> str:
    return resources.files("admc.configs").joinpath("default.toml").read_text()


def load_config(path: str | Path | list[str | Path] | None = None, overrides: list[str] = ()) -> Config:
    """default.toml, overlaid by `path` (if given; a list: each file in turn), overlaid by `section.key=value`
    overrides."""
    values = tomllib.loads(default_config_text())
    paths = path if isinstance(path, list) else [] if path is None else [path]
    for one in paths:
        values = _merge(values, _read_toml(Path(one)), str(one))
    for item in overrides:
        section, key, value = _parse_override(item)
        values = _merge(values, {section: {key: value}}, f"--set {item}")
    sections = {}
    for field in dataclasses.fields(Config):
        cls = typing.get_type_hints(Config)[field.name]
        hints = typing.get_type_hints(cls)
        try:
            section = cls(**{name: _coerce(values[field.name][name], hints[name], name) for name in hints})
            section.check()
        except SettingError as exc:  # a section names its own field: the key is section.field
            raise exc.in_section(field.name) from None
        sections[field.name] = section
    config = Config(**sections)
    _check_test_set_apart(config)
    scored = config.eval.reference_spp
    require(
        scored == 0 or scored > max(config.render.spp),
        "reference_spp",
        f"must be 0 (render.reference_spp) or exceed every input spp (max {max(config.render.spp)}), got {scored}",
        "eval",
    )
    require(
        config.tile.val_set != "ood" or (config.eval.ood_families and config.eval.ood_scenes_per_family > 0),
        "val_set",
        "is 'ood', but eval.ood_families or eval.ood_scenes_per_family leaves the set empty",
        "tile",
    )
    base = config.model.base
    require(
        base == "noisy" or config.tile.oidn_base,
        "oidn_base",
        f"is false, but model.base = {base!r} trains on OIDN's outputs, which tiling stores only when it is true",
        "tile",
    )
    stored = config.tile.refiner_base
    if base not in ("noisy", stored):  # the message names each base's qualities, which "noisy" has not
        raise ConfigError(
            f"config key 'tile.refiner_base': is {stored!r}, but model.base = {base!r} trains on the "
            f"bases of {base!r} (OIDN {_qualities(base)}; the store's: {_qualities(stored)}): "
            f"set model.base = {stored!r}, or tile.refiner_base = {base!r} with a tile.store of its own"
        )
    return config


def _qualities(base: str) -> str:
    """'high' where both branches share a quality, else 'diffuse high, specular fast'."""
    quality = BASE_QUALITIES[base]
    if len(set(quality.values())) == 1:
        return repr(quality["diffuse"])
    return ", ".join(f"{branch} {q}" for branch, q in quality.items())


def _check_test_set_apart(config: Config) -> None:
    """The dedicated test and out-of-family scenes must not be the training corpus's own scenes (same
    seed, same family): scene seeds are seed * SEEDS_PER_CORPUS + k, so another seed is another scene."""
    for name in ("test", "ood"):
        families, count, seed = (
            getattr(config.eval, f"{name}_{key}") for key in ("families", "scenes_per_family", "seed")
        )
        shared = set(config.corpus.families) & set(families)
        require(
            not (count and config.corpus.n_scenes and shared and seed == config.corpus.seed),
            f"{name}_seed",
            f"equals corpus.seed ({config.corpus.seed}): the {name} scenes of {sorted(shared)} would be "
            "training scenes; choose a seed no training corpus uses",
            "eval",
        )
