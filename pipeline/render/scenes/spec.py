"""What identifies a scene: a small, picklable spec from which everything else is derived.

Dask ships specs to worker processes, so a spec holds only a name, a family, a seed, a film
size, the constructs mixed in, and (for user scenes) a path; meshes, textures and Mitsuba objects are rebuilt from it.
"""

from __future__ import annotations

from dataclasses import dataclass

from admc.errors import AdmcError

XML_FAMILY = "xml"
SEEDS_PER_CORPUS = 1_000_000  # scene seeds of corpus seed s are s * SEEDS_PER_CORPUS + k


class SceneError(AdmcError, ValueError):
    """A scene cannot be described or loaded; the message names the file or spec and the problem."""


class NotAScene(SceneError):
    """An .xml file in a scene folder that is no scene of its own (a part other scenes include, a file
    without a camera): left out and named, never a failure."""


@dataclass(frozen=True)
class SceneSpec:
    scene_id: str
    family: str
    seed: int
    resolution: tuple[int, int]
    xml_path: str | None = None
    constructs: tuple[str, ...] = ()  # named constructs mixed into a procedural family's scene

    def __post_init__(self) -> None:
        object.__setattr__(self, "constructs", tuple(self.constructs))  # a list after a JSON round trip
        width, height = self.resolution
        if int(width) <= 0 or int(height) <= 0:
            raise SceneError(f"scene {self.scene_id!r}: resolution must be positive, got {self.resolution}")
        object.__setattr__(self, "resolution", (int(width), int(height)))
        if (self.family == XML_FAMILY) != (self.xml_path is not None):
            raise SceneError(f"scene {self.scene_id!r}: family 'xml' needs an xml_path and only it may have one")
        if self.xml_path is not None and self.constructs:
            raise SceneError(f"scene {self.scene_id!r}: constructs are for procedural families, not XML scenes")

    @property
    def is_xml(self) -> bool:
        return self.family == XML_FAMILY
