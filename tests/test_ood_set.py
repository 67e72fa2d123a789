"""The out-of-family set: a held-out family made of constructs no training family contains, drawn
with its own seed, apart from every training corpus and from the default test set."""

from pathlib import Path

import pytest

from admc.pipeline.config import ConfigError, load_config
from admc.pipeline.render import tasks as render
from admc.pipeline.render.scenes import CONSTRUCTS, FAMILIES, OOD_CONSTRUCTS, SceneSpec, analyse, load_scene, scene_hash
from admc.pipeline.render.scenes.ood import LAYOUTS, OOD_NAMES
from admc.pipeline.stages.evaluate import eval_scenes

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
OOD = ["eval.split=ood"]
# What the OOD constructs bring that Mitsuba names: none of it may appear in a training scene.
OOD_PLUGINS = {"SunskyEmitter", "DirectionalEmitter", "RoughDielectric", "BlendBSDF"}


def training_configs():
    return [load_config(), load_config(CONFIGS / "pretrain.toml"), load_config(CONFIGS / "broad.toml")]


def test_the_ood_split_is_twelve_held_out_scenes_leading_with_every_construct_in_every_layout():
    specs = eval_scenes(load_config(None, OOD))
    assert len(specs) == 12 and {spec.family for spec in specs} == {"ood"}
    assert all(not spec.constructs for spec in specs)
    leads = {
        (OOD_NAMES[(spec.seed % 1_000_000 // len(LAYOUTS)) % len(OOD_NAMES)], LAYOUTS[spec.seed % len(LAYOUTS)])
        for spec in specs
    }
    assert leads == {(name, layout) for name in OOD_NAMES for layout in LAYOUTS}


def test_no_ood_or_test_scene_is_a_training_scene():
    held_out = {scene_hash(spec) for spec in eval_scenes(load_config(None, OOD))}
    tested = {scene_hash(spec) for spec in eval_scenes(load_config())}
    for cfg in training_configs():
        assert "ood" not in cfg.corpus.families
        trained = {scene_hash(spec) for spec in render.corpus(cfg)} - tested
        assert not held_out & trained and not held_out & tested


def test_the_ood_family_and_constructs_are_refused_in_training():
    with pytest.raises(ConfigError, match=r"config key 'corpus.families': \['ood'\] .*held out of training"):
        load_config(None, ["corpus.families=['room', 'ood']"])
    with pytest.raises(ConfigError, match=r"config key 'corpus.constructs': \['sunsky'\] .*out-of-family set"):
        load_config(None, ["corpus.constructs=['projector', 'sunsky']"])
    with pytest.raises(ConfigError, match=r"config key 'eval.ood_seed': equals corpus.seed"):
        load_config(None, ["corpus.held_out_families=[]", "corpus.families=['ood']", "eval.ood_seed=0"])
    assert not set(OOD_CONSTRUCTS) & set(CONSTRUCTS)


def test_ood_scenes_hold_plugins_no_training_scene_has(variant):
    ood_types = set()
    for spec in eval_scenes(load_config(None, OOD + ["render.resolution=[32, 32]"])):
        needs = analyse(load_scene(spec))
        ood_types |= set(needs.bsdf_types) | set(needs.emitter_types)
    assert OOD_PLUGINS <= ood_types
    for family in sorted(set(FAMILIES) - {"ood"}):
        names = tuple(n for n, c in CONSTRUCTS.items() if FAMILIES[family].has_support or not c.needs_support)
        for seed in range(3):
            needs = analyse(load_scene(SceneSpec("t", family, seed, (32, 32), constructs=names)))
            assert not OOD_PLUGINS & (set(needs.bsdf_types) | set(needs.emitter_types)), (family, seed)


def test_checkpoints_can_be_selected_on_the_ood_set(tmp_path):
    """tile.val_set = ood: the store's val split (what validation and checkpoint selection read) is the
    out-of-family set, the corpus is all train; a store whose val split holds other scenes is refused."""
    from conftest import tiny_store_overrides

    from admc.errors import StageError
    from admc.pipeline.stages.dataset import build_dataset
    from admc.pipeline.stages.train import check_splits
    from admc.stores import patches

    overrides = tiny_store_overrides(tmp_path, 32, 32) + ["tile.split=[1.0, 0.0, 0.0]", "eval.ood_scenes_per_family=1"]
    with pytest.raises(ConfigError, match=r"tile.split.*no scene .* falls in the val split"):
        check_splits(load_config(None, overrides))
    cfg = load_config(None, overrides + ["tile.val_set=ood"])
    check_splits(cfg)
    store = build_dataset(cfg, progress=False).store
    assert patches.list_scenes(store, "val") == ["ood-200000000"]
    assert len(patches.list_scenes(store, "train")) == 4
    with pytest.raises(StageError, match=r"val split holds ood-200000000 .*tile.val_set = 'split'.*another tile.store"):
        build_dataset(load_config(None, overrides), progress=False)
