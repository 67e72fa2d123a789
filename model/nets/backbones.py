"""The generator class of each backbone a config can name.

A module of its own because the multi-scale body subclasses the full-resolution one: the base class
cannot import its subclass to build it.
"""

from __future__ import annotations

from .generator import Generator
from .settings import ModelSettings
from .unet import UNetGenerator

GENERATORS: dict[str, type[Generator]] = {"residual": Generator, "unet": UNetGenerator}
"""One class per name in settings.BACKBONES (the names a config may give)."""


def build_generator(config: ModelSettings) -> Generator:
    """The generator of the backbone `config` names."""
    return GENERATORS[config.backbone](config)
