"""The scene corpus: seeded procedural families and users' Mitsuba XML scenes.

Families compose named constructs (`constructs.py`); the `ood` family is held out of training.
Everything is derived from a small picklable `SceneSpec`, so render tasks can run in any
process: `load_scene(spec)` builds the Mitsuba scene, `scene_hash(spec)` keys caches, and
`analyse(scene)` says whether a specular buffer is needed.
"""

from .analysis import SceneNeeds, analyse
from .constructs import CONSTRUCTS
from .families import FAMILIES, procedural_corpus
from .loading import load_scene, scene_description, scene_hash
from .ood import OOD_CONSTRUCTS
from .spec import NotAScene, SceneError, SceneSpec
from .xml_loader import xml_corpus

__all__ = [
    "CONSTRUCTS",
    "FAMILIES",
    "NotAScene",
    "OOD_CONSTRUCTS",
    "SceneError",
    "SceneNeeds",
    "SceneSpec",
    "analyse",
    "load_scene",
    "procedural_corpus",
    "scene_description",
    "scene_hash",
    "xml_corpus",
]
