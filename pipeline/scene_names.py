"""The names of the procedural families and constructs, apart from the code that builds them.

The config checks `[corpus]` and `[eval]` against these names without importing the scene builders
(`render/scenes/`, which sit above the config: render tasks take a Config). `render/scenes/` registers
its builders under exactly these names, in this order (tests/test_scenes.py checks both agree).
"""

from __future__ import annotations

FAMILY_NAMES = ("room", "tabletop", "studio", "preview", "ood")
"""render/scenes/families.py FAMILIES; "ood" is the held-out family (docs/corpus.md)."""
CONSTRUCT_NAMES = (
    "projector",
    "grate",
    "foliage",
    "hdr_sky",
    "bump",
    "rough_texture",
    "thinlens",
    "mirrors",
    "caustic",
)
"""render/scenes/constructs.py CONSTRUCTS: what `corpus.constructs` may mix into the training families."""
OOD_CONSTRUCT_NAMES = ("sunsky", "blinds", "screen", "brushed", "frosted", "patina")
"""render/scenes/ood.py OOD_CONSTRUCTS: the out-of-family set's own constructs, never in training."""
