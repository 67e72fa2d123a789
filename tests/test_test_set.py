"""The default test set: enough images of every family, the hard cases present, and no training scene in it."""

from pathlib import Path

import pytest

from admc.pipeline.config import ConfigError, load_config
from admc.pipeline.render import tasks as render
from admc.pipeline.render.scenes import analyse, load_scene, scene_hash
from admc.pipeline.stages.evaluate import EvalStageError, eval_scenes

PRETRAIN = Path(__file__).resolve().parents[1] / "configs" / "pretrain.toml"
BROAD = Path(__file__).resolve().parents[1] / "configs" / "broad.toml"


def test_default_test_set_has_eight_scenes_of_every_family():
    cfg = load_config()
    families = [spec.family for spec in eval_scenes(cfg)]
    assert all(families.count(family) >= 8 for family in ("room", "tabletop", "studio"))


def test_no_test_scene_is_a_training_scene_of_the_demo_or_the_pretraining_corpora():
    test = {scene_hash(spec) for spec in eval_scenes(load_config())}
    for cfg in (load_config(), load_config(PRETRAIN), load_config(BROAD)):
        trained = {scene_hash(spec) for spec in render.corpus(cfg)} - {scene_hash(s) for s in eval_scenes(cfg)}
        assert not test & trained


def test_default_test_set_holds_the_hard_cases(variant):
    """A diffuse-only scene, a mirror or glass, and a studio object in a black void (no environment emitter)."""
    specs = eval_scenes(load_config())
    needs = {spec.scene_id: analyse(load_scene(spec)) for spec in specs}
    assert any(not n.has_specular for n in needs.values())
    assert any({"SmoothConductor", "SmoothDielectric"} & set(n.bsdf_types) for n in needs.values())
    environment = {"EnvironmentMapEmitter", "ConstantBackgroundEmitter"}
    assert any(spec.family == "studio" and not environment & set(needs[spec.scene_id].emitter_types) for spec in specs)


def test_a_test_seed_equal_to_the_corpus_seed_is_refused():
    with pytest.raises(ConfigError, match=r"eval.test_seed.*equals corpus.seed \(0\).*training scenes"):
        load_config(None, ["eval.test_seed=0"])
    assert load_config(None, ["eval.test_seed=0", "eval.test_scenes_per_family=0"]).eval.test_seed == 0


def test_an_unknown_test_family_is_named_with_its_key():
    with pytest.raises(
        EvalStageError, match=r"config key 'eval.test_families': unknown procedural families \['moon'\]"
    ):
        eval_scenes(load_config(None, ["eval.test_families=['moon']"]))
