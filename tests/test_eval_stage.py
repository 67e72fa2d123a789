"""`admc-pipe eval` end to end on a tiny corpus: renders the test split, writes every output a person reads."""

import json
from html import escape as html_escape
import subprocess
import sys
from pathlib import Path

import pytest

from admc.common.metrics import METRICS
from admc.pipeline.config import ConfigError, load_config
from admc.pipeline.evaluation.baselines import optix_unavailable_reason
from admc.pipeline.evaluation.html import ReportImage, report_group
from admc.pipeline.stages.evaluate import REPORT_SCENES, EvalStageError, eval_scenes, run_eval
from admc.stores.exr import read_image

ADMC = str(Path(sys.executable).parent / "admc-pipe")


def overrides(workdir, split="[0.0, 0.0, 1.0]"):
    return [
        f"run.workdir='{workdir}'",
        "run.scheduler=sync",
        "render.resolution=[32, 32]",
        "render.spp=[2, 4]",
        "render.reference_spp=32",
        "corpus.n_scenes=2",
        f"tile.split={split}",
        "eval.repeats=1",
        "eval.test_scenes_per_family=0",
    ]


def test_eval_writes_tables_plot_and_html(tmp_path, variant):
    outcome = run_eval(load_config(None, overrides(tmp_path)), progress=False)
    assert outcome.scene_ids == [s.scene_id for s in eval_scenes(load_config(None, overrides(tmp_path)))]
    files = outcome.result.files
    for name in ("table1_md", "table1_csv", "results_json", "per_image_csv", "error_vs_time", "equal_time"):
        assert files[name].is_file() and files[name].stat().st_size > 0, name
    results = json.loads(files["results_json"].read_text())
    methods = {row["method"] for row in results["table"]}
    html = outcome.report.read_text()
    assert outcome.report.name == "index.html" and "oidn" in html and "data:image/png;base64," in html
    assert html.count("Table 1") == 1, "one heading for the table (the Markdown title line is left out)"
    assert "HDR-FLIP ↓ Avg." in html and "<dt>HDR-FLIP</dt><dd>HDR-FLIP (Andersson" in html  # column, definition
    assert all(0.0 <= row["average"]["hdr_flip"] <= 1.0 for row in results["table"])
    why_no_optix = optix_unavailable_reason()
    if why_no_optix is None:  # a CUDA machine: OptiX is in every table
        assert methods == {"noisy", "oidn", "optix"} and results["not_run"] == {}
    else:  # it is absent, and every output says why
        assert methods == {"noisy", "oidn"} and results["not_run"] == {"optix": why_no_optix}
        assert f"**Not run:** optix: {why_no_optix}" in files["table1_md"].read_text()
        assert "Not run:" in html and html_escape(why_no_optix) in html


def test_oidns_prefiltered_route_is_a_column_of_its_own_where_asked(tmp_path, variant):
    """eval.oidn_prefiltered: OIDN's final-frame route (guides prefiltered, then cleanAux) beside its default
    route, scored like it, on the same renders; another image than the default route's."""
    cfg = load_config(None, [*overrides(tmp_path), "eval.oidn_prefiltered=true"])
    outcome = run_eval(cfg, progress=False)
    rows = {(row.method, row.spp): row for row in outcome.result.table}
    assert {method for method, _ in rows} >= {"noisy", "oidn", "oidn-prefiltered"}
    for spp in (2, 4):
        prefiltered, default = rows[("oidn-prefiltered", spp)].average, rows[("oidn", spp)].average
        assert all(0.0 <= prefiltered[m] < float("inf") for m in ("relmse", "one_minus_ssim", "hdr_flip"))
        assert prefiltered["relmse"] != default["relmse"]
        assert prefiltered["relmse"] < rows[("noisy", spp)].average["relmse"]
    with pytest.raises(ConfigError, match="oidn_prefiltered"):
        load_config(None, [*overrides(tmp_path), "eval.oidn_prefiltered=3"])


def test_eval_scores_against_references_at_eval_reference_spp_and_tiling_keeps_its_own(tmp_path, variant):
    """eval.reference_spp renders the scored scenes' references at that spp (apart from the training
    references of render.reference_spp, which stay cached for tiling); the sidecars and Table 1's reference
    cost say which spp was scored against."""
    from admc.pipeline.stages.render import render_corpus

    cfg = load_config(None, overrides(tmp_path) + ["eval.reference_spp=64", "eval.optix='off'"])
    training = render_corpus(cfg, progress=False)
    outcome = run_eval(cfg, progress=False)
    assert json.loads(outcome.result.files["results_json"].read_text())["reference_cost"]["spp"] == [64]
    for scene_id in outcome.scene_ids:
        scored = json.loads((tmp_path / "renders" / scene_id / "reference.json").read_text())
        assert scored["spp"] == 64 and scored["reference"]
    assert [s["spp"] for s in training.sidecars if s["reference"]] == [32, 32]  # tiling's references, still cached
    with pytest.raises(ConfigError, match="eval.reference_spp"):
        load_config(None, overrides(tmp_path) + ["eval.reference_spp=3"])  # not above the inputs' 4 spp


def test_eval_page_shows_the_written_images_and_no_npy_is_left(tmp_path, variant):
    """The page's figures, made while evaluation held the images, are the ones the written EXRs give:
    for every (scene, spp) shown, the same encoded PNGs and metrics, in the order evaluated."""
    outcome = run_eval(load_config(None, overrides(tmp_path) + ["eval.optix='off'"]), progress=False)
    out, page = outcome.report.parent, outcome.report.read_text()
    assert not list(out.rglob("*.npy"))
    metrics = {
        (r.scene_id, r.spp, r.method): {m.label: getattr(r, m.key) for m in METRICS} for r in outcome.result.records
    }
    shown = outcome.result.scenes[:REPORT_SCENES]
    assert len(shown) == 2 and page.count('<section class="group"') == 2 * 2
    for index, (scene, spp) in enumerate((s, spp) for s in shown for spp in sorted(s.outputs)):
        outputs = {name: read_image(path) for name, path in scene.outputs[spp].items()}
        item = ReportImage(
            scene.scene_id,
            spp,
            read_image(scene.reference),
            outputs,
            {name: metrics[(scene.scene_id, spp, name)] for name in outputs},
        )
        assert f'<section class="group" id="group-{index}">{report_group(item).body}</section>' in page


@pytest.mark.skipif(optix_unavailable_reason() is None, reason="this machine runs OptiX")
def test_eval_optix_on_without_cuda_is_a_clear_error_before_rendering(tmp_path, variant):
    cfg = load_config(None, overrides(tmp_path) + ["eval.optix='on'"])
    with pytest.raises(EvalStageError, match=r"eval.optix = on, but .*CUDA.*set eval.optix = auto"):
        run_eval(cfg, progress=False)
    assert not (tmp_path / "renders").exists(), "the error must come before any render work"


def test_eval_optix_off_is_stated_and_oidn_runs_at_the_configured_quality(tmp_path, variant):
    cfg = load_config(None, overrides(tmp_path) + ["eval.optix='off'", "eval.oidn_quality='fast'"])
    outcome = run_eval(cfg, progress=False)
    assert outcome.result.not_run == {"optix": "turned off (eval.optix = off)"}
    assert {row.method for row in outcome.result.table} == {"noisy", "oidn-fast"}


def test_empty_test_split_is_a_clear_error(tmp_path, variant):
    with pytest.raises(EvalStageError, match="no scene of the corpus falls in the 'test' split"):
        run_eval(load_config(None, overrides(tmp_path, split="[1.0, 0.0, 0.0]")), progress=False)


def test_cli_eval_prints_table_and_report_path(tmp_path, variant):
    args = [item for s in overrides(tmp_path) for item in ("--set", s)]
    out = subprocess.run([ADMC, "eval", "--no-model", *args], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "oidn" in out.stdout and "HTML report:" in out.stdout
    header = next(line for line in out.stdout.splitlines() if line.startswith("| spp | Denoiser |"))
    assert header.endswith("relMSE − floor ↓ Avg. |"), "off a terminal the Markdown table must not be wrapped"


def test_eval_on_a_users_own_xml_scenes_at_their_film_size(tmp_path, variant):
    """The recipe of docs/usage.md: a folder of the user's scenes as the whole test set, at each file's film size."""
    from test_scenes import write_kitchen_scene

    scenes = write_kitchen_scene(tmp_path / "my_scenes").parent
    cfg = load_config(
        None,
        [
            f"run.workdir='{tmp_path / 'work'}'",
            "run.scheduler=sync",
            "render.spp=[2]",
            "render.reference_spp=16",
            "corpus.n_scenes=0",
            f"corpus.xml_dirs=['{scenes}']",
            "corpus.xml_resolution='film'",
            "tile.split=[0.0, 0.0, 1.0]",
            "eval.repeats=1",
            "eval.test_scenes_per_family=0",
        ],
    )
    outcome = run_eval(cfg, progress=False)
    assert outcome.scene_ids == ["xml-kitchen"]
    (scene,) = outcome.result.scenes
    assert read_image(scene.reference).shape == (30, 40, 3), "the film's 40x30, not render.resolution"
    assert {row.method for row in outcome.result.table} >= {"noisy", "oidn"}


def test_weights_columns_are_named_by_the_eval_stage(tmp_path):
    from admc.pipeline.stages.evaluate import named_weights

    # one unnamed file: named after the base it records when loaded ("admc" or "admc+oidn")
    assert named_weights(["runs/a/weights-fp16.pt"]) == [(None, Path("runs/a/weights-fp16.pt"))]
    assert [n for n, _ in named_weights(["runs/a/weights-fp16.pt", "base=x.pt"])] == ["admc-a", "base"]
    with pytest.raises(EvalStageError, match=r"would be named \['admc-a', 'admc-a'\]; name them apart"):
        named_weights(["runs/a/weights-fp16.pt", "other/a/checkpoint.pt"])


@pytest.mark.parametrize("ensemble,dark_pass,rows", [(1, "false", 2), (4, "true", 1)])
def test_the_ensemble_and_dark_pass_row_has_its_own_name_and_settings(tmp_path, ensemble, dark_pass, rows):
    from admc.pipeline.evaluation.scoring import _check_denoisers
    from admc.pipeline.stages.evaluate import learned_denoisers
    from admc.pipeline.weights import WEIGHTS_DIR

    cfg = load_config(
        None,
        overrides(tmp_path)
        + [f"eval.ensemble={ensemble}", f"eval.dark_pass={dark_pass}", "eval.also_ensemble_dark=true"],
    )
    models = learned_denoisers(cfg, [str(WEIGHTS_DIR / "admc-small-pretrained.pt")], device="cpu")
    assert [(m.name, m.ensemble, m.dark_pass) for m in models] == [
        ("admc", ensemble, dark_pass == "true"),
        ("admc-ens4+dark", 4, True),
    ][:rows]  # no row twice
    _check_denoisers(models)  # names evaluate() accepts (they name image files)
