"""Config: defaults load, overlays and overrides apply, bad keys and values are errors naming the key."""

from pathlib import Path

import pytest

from admc.pipeline.config import ConfigError, load_config

REPO = Path(__file__).resolve().parents[1]


def test_default_config_is_laptop_sized():
    cfg = load_config()
    assert cfg.render.resolution == (256, 256)
    assert cfg.render.reference_spp > max(cfg.render.spp)
    assert cfg.corpus.n_scenes > 0 and cfg.corpus.families


def test_paper_config_overlays_default():
    cfg = load_config(REPO / "configs" / "paper.toml")
    assert cfg.corpus.n_scenes == 1000
    assert cfg.render.resolution == (1280, 720)
    assert cfg.render.reference_spp == 16384
    assert cfg.run.workdir == load_config().run.workdir  # untouched keys keep the default


def test_overrides_parse_toml_values_and_bare_strings():
    cfg = load_config(None, ["render.spp=[2, 8]", "run.scheduler=tcp://10.0.0.1:8786", "corpus.seed=7"])
    assert cfg.render.spp == (2, 8)
    assert cfg.run.scheduler == "tcp://10.0.0.1:8786"
    assert cfg.corpus.seed == 7


@pytest.mark.parametrize(
    "override, key",
    [
        ("render.sppp=4", "render.sppp"),
        ("rendr.spp=[4]", "rendr"),
        ("render.spp='4'", "render.spp"),
        ("render.spp=[0, 4]", "render.spp"),
        ("render.resolution=[32]", "render.resolution"),
        ("render.reference_spp=4", "render.reference_spp"),
        ("corpus.n_scenes=true", "corpus.n_scenes"),
        ("run.workers=-1", "run.workers"),
    ],
)
def test_bad_values_name_the_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(None, [override])


def test_unknown_key_in_file_names_file_and_key(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text("[render]\nsamples = 4\n")
    with pytest.raises(ConfigError, match=r"render\.samples.*mine\.toml"):
        load_config(path)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[render\n")
    with pytest.raises(ConfigError, match="bad.toml"):
        load_config(bad)


def test_the_paper_config_is_the_settings_defaults():
    """The defaults are what a checkpoint missing a key is read with (ModelSettings.from_saved), and
    the paper's scale as the docstrings say."""
    from admc.model.nets.settings import ModelSettings
    from admc.model.train_settings import TrainSettings

    paper = load_config(REPO / "configs" / "paper.toml")
    assert (paper.model, paper.train) == (ModelSettings(), TrainSettings())


@pytest.mark.parametrize(
    "override, key",
    [
        ("train.batch_size=0", "train.batch_size"),
        ("model.mode='cat'", "model.mode"),
        ("train.lr_milestones=[5, 3]", "train.lr_milestones"),
        ("train.adversarial=1", "train.adversarial"),
        ("train.precision='float16'", "train.precision"),
        ("train.l1_floor=0", "train.l1_floor"),
        ("train.ssim_weight=-0.5", "train.ssim_weight"),
        ("train.select_metric='ssim'", "train.select_metric"),
        ("eval.ensemble=3", "eval.ensemble"),
        ("eval.engine='tensorrt'", "eval.engine"),
    ],
)
def test_model_and_train_errors_name_the_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(None, [override])


def test_pretrain_corpora_are_disjoint_from_the_default_corpus_and_have_their_families():
    """pretrain.toml: the three original families; broad.toml: every family but the held-out ones."""
    from admc.pipeline.render.scenes import FAMILIES
    from admc.pipeline.render.tasks import corpus

    default = load_config()
    for name, families in (
        ("pretrain", {"room", "tabletop", "studio"}),
        ("broad", set(FAMILIES) - set(default.corpus.held_out_families)),
    ):
        specs = corpus(load_config(REPO / "configs" / f"{name}.toml"))
        assert len(specs) >= 100 and {s.family for s in specs} == families, name
        assert not {(s.family, s.seed) for s in specs} & {(s.family, s.seed) for s in corpus(default)}, name
