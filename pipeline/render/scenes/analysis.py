"""What a loaded scene needs from the renderer: is there any specular light transport at all?

A scene whose BSDFs have no glossy or delta lobe has nothing in the specular buffer, so the
pipeline skips rendering, storing, training and denoising it. Wrappers (twosided, blendbsdf,
mask) report the union of their children's lobes in `flags()`, so the top-level flags suffice.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SceneNeeds:
    has_specular: bool
    bsdf_types: tuple[str, ...]  # Mitsuba class names, nested BSDFs included, sorted
    emitter_types: tuple[str, ...]  # Mitsuba class names, sorted


def _specular_mask() -> int:
    """Glossy and delta lobes. `BSDFFlags.Delta` also holds `Null` (an alpha mask or a medium
    boundary passing light straight on), which scatters nothing into the specular buffer."""
    import mitsuba as mi

    flags = mi.BSDFFlags
    return int(flags.Glossy) | int(flags.DeltaReflection) | int(flags.DeltaTransmission) | int(flags.Delta1D)


def is_specular(bsdf) -> bool:
    """True when the BSDF (or anything nested in it) has a glossy or delta lobe."""
    return (int(bsdf.flags()) & _specular_mask()) != 0


def _class_names(objects, kind) -> set[str]:
    """Class names of `objects` and of every object of type `kind` nested inside them."""
    import mitsuba as mi

    names = set()
    for obj in objects:
        names.add(obj.class_name())
        names.update(node.class_name() for node in mi.traverse(obj).hierarchy if isinstance(node, kind))
    return names


def analyse(scene) -> SceneNeeds:
    import mitsuba as mi

    bsdfs = [shape.bsdf() for shape in scene.shapes() if shape.bsdf() is not None]
    emitters = list(scene.emitters())
    return SceneNeeds(
        has_specular=any(is_specular(bsdf) for bsdf in bsdfs),
        bsdf_types=tuple(sorted(_class_names(bsdfs, mi.BSDF))),
        emitter_types=tuple(sorted({emitter.class_name() for emitter in emitters})),
    )
