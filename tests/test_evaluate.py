"""Evaluation on a real tiny render set (2 scenes x 2 spp, 32x32) with the noisy input and OIDN on CPU."""

import csv
import gc
import json
import math
import shutil
import weakref
from collections import defaultdict

import flip_evaluator
import numpy as np
import pyoidn
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from admc.common.buffers import BEAUTY
from admc.common.metrics import METRICS, count_nonfinite, score, to_ldr
from admc.pipeline.config import load_config
from admc.pipeline.evaluation.baselines import (
    Denoiser,
    NoisyInput,
    OidnDenoiser,
    OptixDenoiser,
    mitsuba_sensor_normals,
    noisy_color,
    optix_unavailable_reason,
    time_denoiser,
)
from admc.pipeline.evaluation.scoring import evaluate
from admc.pipeline.evaluation.inputs import find_test_images, read_reference
from admc.pipeline.evaluation.records import PATH_TRACER, EvalError, best_percent
from admc.pipeline.render.tasks import view_space_normals
from admc.pipeline.stages.evaluate import ReportFigures
from admc.pipeline.stages.render import render_corpus
from admc.stores.exr import exr_layers, read_exr, read_image, write_exr

METRIC_KEYS = [m.key for m in METRICS]


@pytest.fixture(scope="module")
def renders(variant, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eval_renders")
    cfg = load_config(
        None,
        [
            f"run.workdir='{tmp}'",
            "run.scheduler=sync",
            "render.resolution=[32, 32]",
            "render.spp=[2, 4]",
            "render.reference_spp=64",
            "corpus.n_scenes=2",
        ],
    )
    return render_corpus(cfg, progress=False).renders_dir


@pytest.fixture(scope="module")
def handed():
    """Every ScoredImage the `evaluated` run handed to its on_image, in order."""
    return []


@pytest.fixture(scope="module")
def evaluated(renders, handed, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval_out")
    images = find_test_images(renders)
    return evaluate(
        images, [NoisyInput(), OidnDenoiser()], out, progress=False, repeats=1, warmup=0, on_image=handed.append
    ), out


def _read_table(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_find_test_images_reads_folders_and_sidecars(renders):
    images = find_test_images(renders)
    assert [(t.scene_id, t.spp) for t in images] == [
        (s, spp) for s in sorted(p.name for p in renders.iterdir()) for spp in (2, 4)
    ]
    for t in images:
        side = json.loads(t.noisy_path.with_suffix(".json").read_text())
        assert t.render_seconds == side["render_seconds"] > 0
        assert t.reference_path.name == "reference.exr"
        reference_side = json.loads(t.reference_path.with_suffix(".json").read_text())
        assert (t.reference_spp, t.reference_seconds) == (64, reference_side["render_seconds"])
    one = images[0].scene_id
    assert {t.scene_id for t in find_test_images(renders, [one])} == {one}


def test_find_test_images_names_what_is_missing(renders, tmp_path):
    scene = sorted(p for p in renders.iterdir())[0]
    broken = tmp_path / "renders" / scene.name
    shutil.copytree(scene, broken)  # follows the links: real files
    with pytest.raises(EvalError, match="no such scene folder"):
        find_test_images(tmp_path / "renders", ["nope"])
    (broken / "spp0004.json").unlink()
    with pytest.raises(EvalError, match=r"spp0004\.json: sidecar missing"):
        find_test_images(tmp_path / "renders")
    (broken / "reference.exr").unlink()
    with pytest.raises(EvalError, match=f"{scene.name}: reference.exr missing"):
        find_test_images(tmp_path / "renders")
    with pytest.raises(EvalError, match="no renders folder"):
        find_test_images(tmp_path / "absent")


def test_writes_every_output(evaluated):
    result, out = evaluated
    for name in ("per_image.csv", "results.json", "table1.md", "table1.csv", "error_vs_time.png", "equal_time.md"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert set(result.files.values()) == {
        out / n
        for n in ("per_image.csv", "results.json", "table1.md", "table1.csv", "error_vs_time.png", "equal_time.md")
    }
    assert (out / "error_vs_time.png").read_bytes()[:4] == b"\x89PNG"
    doc = json.loads((out / "results.json").read_text())
    assert set(doc["metrics"]) == set(METRIC_KEYS)
    assert all(doc["metrics"][k]["definition"] for k in METRIC_KEYS)
    assert doc["devices"]["oidn"].startswith("cpu (")
    assert doc["timing"]["repeats"] == 1 and len(doc["images"]) == 8 and len(doc["path_tracer"]) == 4
    md = (out / "table1.md").read_text()
    assert "B.P." in md and "rtol" in md and "cpu (" in md and "(ref^2 + 0.01)" in md
    assert "| HDR-FLIP ↓ Avg. | HDR-FLIP ↓ B.P. |" in md and "**HDR-FLIP**: HDR-FLIP (Andersson" in md
    # the noisy-input row is the raw path tracer itself, so equal time compares only denoisers to it
    assert {row["method"] for row in doc["equal_time"]} == {"oidn"}
    equal_md = (out / "equal_time.md").read_text()
    assert equal_md.count("\n| oidn |") == 2 and "\n| noisy |" not in equal_md
    per_image = _read_table(out / "per_image.csv")
    assert len(per_image) == 12 and {r["method"] for r in per_image} == {"path tracer", "noisy", "oidn"}
    assert all(0.0 <= float(r["hdr_flip"]) <= 1.0 for r in per_image)
    assert all(0.0 <= image["hdr_flip"] <= 1.0 for image in doc["images"])
    for scene in result.scenes:
        assert read_image(scene.reference).shape == (32, 32, 3)
        assert set(scene.inputs) == {2, 4} and set(scene.outputs[2]) == {"noisy", "oidn"}
    assert not list(out.rglob("*.npy"))
    written = {p.relative_to(out).as_posix() for p in (out / "images").rglob("*") if p.is_file()}
    assert written == {
        f"images/{s.scene_id}/{name}.exr"
        for s in result.scenes
        for name in (
            "reference",
            "spp0002_input",
            "spp0004_input",
            "spp0002_noisy",
            "spp0002_oidn",
            "spp0004_noisy",
            "spp0004_oidn",
        )
    }


def test_exrs_hold_the_scored_images_and_on_image_had_them_in_memory(renders, evaluated, handed):
    """Each (scene, spp) is handed over once, in order, with the images that were scored; a person opening
    the written EXRs (plain RGB, float32, read here by OpenImageIO as a viewer would) sees exactly those."""
    result, out = evaluated
    assert [(h.scene_id, h.spp) for h in handed] == [(t.scene_id, t.spp) for t in find_test_images(renders)]
    doc = json.loads((out / "results.json").read_text())
    listed = {(d["scene_id"], d["spp"], d["method"]): d["image"] for d in doc["images"] + doc["path_tracer"]}
    for h, test in zip(handed, find_test_images(renders)):
        np.testing.assert_array_equal(h.reference, read_reference(test.reference_path)[0])
        np.testing.assert_array_equal(h.noisy, noisy_color(read_exr(test.noisy_path)))
        assert list(h.records) == [PATH_TRACER, "noisy", "oidn"] and list(h.outputs) == ["noisy", "oidn"]
        assert h.records[PATH_TRACER] in result.path_tracer
        assert all(h.records[name] in result.records for name in h.outputs)
        for name, image in {PATH_TRACER: h.noisy, **h.outputs}.items():
            path = h.records[name].image
            assert exr_layers(path) == [BEAUTY] and listed[(h.scene_id, h.spp, name)] == str(path.relative_to(out))
            np.testing.assert_array_equal(read_image(path), image)
            rescored = score(read_image(path), read_image(out / "images" / h.scene_id / "reference.exr"))
            assert rescored == {k: getattr(h.records[name], k) for k in METRIC_KEYS}, "per_image.csv, from the files"
        np.testing.assert_array_equal(read_image(out / "images" / h.scene_id / "reference.exr"), h.reference)


class _Watcher:
    """A real (if useless) denoiser, the noisy colour, that counts at every run how many images handed to
    on_image for an earlier scene are still alive: evaluation must hold only the scene it works on."""

    name = "watcher"
    device = "cpu"

    def __init__(self):
        self.handed, self.alive = [], []

    def denoise(self, layers):
        gc.collect()
        self.alive.append(sum(ref() is not None for ref in self.handed))
        return noisy_color(layers)

    def synchronize(self):
        pass


def test_evaluation_and_the_report_figures_hold_one_scene_at_a_time(renders, tmp_path):
    images = [t for t in find_test_images(renders) if t.spp == 2]  # one test image per scene
    watcher, figures = _Watcher(), ReportFigures(limit=1)

    def on_image(scored):
        figures(scored)
        watcher.handed += [weakref.ref(a) for a in (scored.reference, scored.noisy, *scored.outputs.values())]

    # the watcher runs after OIDN: pyoidn keeps its last call's buffers bound to its cached filter until
    # its next call (one image, its own business), so by then the earlier scene's OIDN output is released
    evaluate(
        images,
        [NoisyInput(), OidnDenoiser(), watcher],
        tmp_path,
        progress=False,
        repeats=1,
        warmup=0,
        on_image=on_image,
    )
    assert len(images) == 2 and len(watcher.handed) == 2 * 5
    assert watcher.alive == [0, 0], "the first scene's images outlived it"
    assert figures.scene_ids == [images[0].scene_id] and len(figures.groups) == 1
    assert all(isinstance(g.body, str) for g in figures.groups)


def test_reference_render_time_ends_the_raw_curve(renders, evaluated):
    result, out = evaluated
    sidecars = [json.loads((folder / "reference.json").read_text()) for folder in sorted(renders.iterdir())]
    expected = float(np.mean([side["render_seconds"] for side in sidecars]))
    assert result.reference_cost == {"spp": [64], "seconds": pytest.approx(expected)}
    assert json.loads((out / "results.json").read_text())["reference_cost"]["seconds"] == pytest.approx(expected)
    assert (
        f"The references (64 spp, relMSE 0 by definition) took {expected:.4g} s" in (out / "equal_time.md").read_text()
    )


def test_best_percent_columns_sum_to_100(evaluated):
    _, out = evaluated
    rows = _read_table(out / "table1.csv")
    assert {int(r["spp"]) for r in rows} == {2, 4}
    for spp in (2, 4):
        at = [r for r in rows if int(r["spp"]) == spp]
        assert len(at) == 2
        for key in METRIC_KEYS:
            assert sum(float(r[f"{key}_bp"]) for r in at) == pytest.approx(100.0, abs=1e-9)


def test_best_percent_splits_ties():
    per_image = [
        {"a": 1.0, "b": 1.0, "c": 2.0},  # a, b tie for lowest
        {"a": 0.5, "b": 0.7, "c": 0.5 * (1 + 1e-8)},  # a, c equal within rtol 1e-6
        {"a": 3.0, "b": 3.0, "c": 3.0},  # three-way tie
        {"a": 0.9, "b": 0.1, "c": 0.2},  # b alone
    ]
    lower = best_percent(per_image, lower_is_better=True)
    assert lower == pytest.approx(
        {"a": 25 * (1 / 2 + 1 / 2 + 1 / 3), "b": 25 * (1 / 2 + 1 / 3 + 1), "c": 25 * (1 / 2 + 1 / 3)}
    )
    assert sum(lower.values()) == pytest.approx(100.0, abs=1e-12)
    higher = best_percent(per_image, lower_is_better=False)
    assert higher == pytest.approx({"a": 25 * (1 / 3 + 1), "b": 25 * (1 / 3 + 1), "c": 25 * (1 + 1 / 3)})


def _independent_scores(image, ref):
    """The metrics written out again from their definitions, SSIM/PSNR by scikit-image, HDR-FLIP by NVIDIA's
    package with its own exposure range (these references are lit in most pixels)."""
    a, b = to_ldr(image), to_ldr(ref)
    image, ref = image.astype(np.float64), ref.astype(np.float64)
    return {
        "one_minus_ssim": 1
        - structural_similarity(
            a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, channel_axis=-1, data_range=255
        ),
        "psnr": min(peak_signal_noise_ratio(b, a, data_range=255), 100.0),
        "relmse": float(np.mean((image - ref) ** 2 / (ref**2 + 0.01))),
        "hdr_flip": flip_evaluator.evaluate(
            np.maximum(ref, 0).astype(np.float32), np.maximum(image, 0).astype(np.float32), "HDR"
        )[1],
    }


def test_table_matches_independent_recomputation(renders, evaluated):
    result, out = evaluated
    scores = defaultdict(list)
    for t in find_test_images(renders):
        ref = read_exr(t.reference_path)
        ref = ref["diffuse"] + ref.get("specular", 0)
        layers = read_exr(t.noisy_path)
        noisy = layers["diffuse"] + layers.get("specular", 0)
        oidn = pyoidn.denoise(noisy, layers["albedo"], layers["normal"], hdr=True, quality="high")
        saved = read_image(
            next(r.image for r in result.records if (r.scene_id, r.spp, r.method) == (t.scene_id, t.spp, "oidn"))
        )
        np.testing.assert_allclose(saved, oidn, rtol=1e-6, atol=1e-7)
        scores[(t.spp, "noisy")].append(_independent_scores(noisy, ref))
        scores[(t.spp, "oidn")].append(_independent_scores(oidn, ref))
    rows = _read_table(out / "table1.csv")
    assert len(rows) == len(scores) == 4
    for row in rows:
        mine = scores[(int(row["spp"]), row["denoiser"])]
        assert int(row["n_images"]) == len(mine) == 2
        for key in METRIC_KEYS:
            assert float(row[f"{key}_avg"]) == pytest.approx(np.mean([s[key] for s in mine]), rel=1e-6, abs=1e-9)


def test_oidn_beats_noisy_input_at_lowest_spp(evaluated):
    result, _ = evaluated
    row = {r.method: r for r in result.table if r.spp == 2}
    assert row["oidn"].average["relmse"] < 0.5 * row["noisy"].average["relmse"]
    assert row["oidn"].best_percent["relmse"] == 100.0
    assert row["oidn"].average["hdr_flip"] < row["noisy"].average["hdr_flip"]
    noisy = {r.scene_id: r.relmse for r in result.records if r.spp == 2 and r.method == "noisy"}
    for r in result.records:
        if r.spp == 2 and r.method == "oidn":
            assert r.relmse < noisy[r.scene_id]


def test_normals_reach_optix_in_mitsubas_sensor_frame(variant):
    """mi.OptixDenoiser wants normals in the frame of the sensor that rendered the image; check our
    stored view-space normals, converted back, against Mitsuba's own world-to-sensor transform."""
    import mitsuba as mi

    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "perspective",
                "to_world": mi.ScalarTransform4f().look_at(origin=[3, 1.5, -2], target=[0, 0.3, 0.4], up=[0.2, 1, 0.1]),
            },
        }
    )
    rng = np.random.default_rng(3)
    world = rng.normal(size=(6, 5, 3))
    world /= np.linalg.norm(world, axis=-1, keepdims=True)
    to_sensor = scene.sensors()[0].world_transform().inverse()
    flat = world.reshape(-1, 3)
    expected = np.array(to_sensor @ mi.Vector3f(flat[:, 0], flat[:, 1], flat[:, 2])).T.reshape(world.shape)
    ours = mitsuba_sensor_normals(view_space_normals(world.astype(np.float32), scene))
    np.testing.assert_allclose(ours, expected, atol=1e-5)
    # and the convention itself: a normal pointing to the image's right is -x for Mitsuba's sensor
    np.testing.assert_array_equal(mitsuba_sensor_normals(np.float32([[1, 0, 0]])), [[-1, 0, 0]])


def test_optix_refuses_clearly_where_it_cannot_run():
    reason = optix_unavailable_reason()
    if reason is None:
        pytest.skip("this machine runs OptiX (see the GPU test below)")
    assert "cuda_ad_rgb" in reason
    with pytest.raises(RuntimeError, match="the OptiX denoiser cannot run: .*cuda_ad_rgb"):
        OptixDenoiser()


@pytest.mark.skipif(optix_unavailable_reason() is not None, reason="needs Mitsuba's cuda_ad_rgb variant and a GPU")
def test_optix_beats_noisy_input_on_a_rendered_image(renders, tmp_path):
    images = [i for i in find_test_images(renders) if i.spp == 2]
    result = evaluate(images, [NoisyInput(), OptixDenoiser()], tmp_path, progress=False, repeats=2, warmup=1)
    row = {r.method: r for r in result.table}
    assert row["optix"].average["relmse"] < 0.5 * row["noisy"].average["relmse"]
    assert row["optix"].device.startswith("cuda (") and row["optix"].nonfinite == 0
    odd = _synthetic_layers(37, 129)
    odd["diffuse"][3, 3] = np.nan
    image = OptixDenoiser().denoise(odd)
    assert image.shape == (37, 129, 3) and np.isfinite(image).all()


def test_nan_in_noisy_input_is_reported_not_fatal(renders, tmp_path):
    scene = sorted(renders.iterdir())[0]
    copy = tmp_path / "renders" / scene.name
    shutil.copytree(scene, copy)
    layers = read_exr(copy / "spp0002.exr")
    layers["diffuse"][5, 7, :] = np.nan
    layers["diffuse"][10, 3, 1] = np.inf
    write_exr(copy / "spp0002.exr", layers)
    result = evaluate(
        find_test_images(tmp_path / "renders"),
        [NoisyInput(), OidnDenoiser()],
        tmp_path / "out",
        progress=False,
        repeats=1,
        warmup=0,
    )
    raw = {r.spp: r for r in result.path_tracer}
    assert raw[2].nonfinite == 4 and raw[4].nonfinite == 0
    by_method = {(r.method, r.spp): r for r in result.records}
    assert by_method[("noisy", 2)].nonfinite == 4
    assert by_method[("oidn", 2)].nonfinite == 0
    assert np.isfinite(read_image(by_method[("oidn", 2)].image)).all()
    assert count_nonfinite(read_image(raw[2].image)) == 4, "the input EXR keeps what was scored, NaN/Inf too"
    assert all(math.isfinite(getattr(r, k)) for r in result.records for k in METRIC_KEYS)
    assert next(r for r in result.table if (r.spp, r.method) == (2, "noisy")).nonfinite == 4
    assert "noisy inputs 4" in (tmp_path / "out" / "table1.md").read_text()


def _synthetic_layers(h, w, seed=0):
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return {
        "diffuse": rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32),
        "specular": rng.gamma(0.5, 0.2, (h, w, 3)).astype(np.float32),
        "albedo": rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
        "normal": normal,
    }


@pytest.mark.parametrize("size", [(1, 1), (127, 129), (37, 4000)])
def test_odd_sizes_go_through_oidn_and_metrics(size):
    layers = _synthetic_layers(*size)
    ref = layers["diffuse"] + layers["specular"]
    denoiser = OidnDenoiser(quality="fast")
    assert denoiser.name == "oidn-fast" and isinstance(denoiser, Denoiser)
    image, seconds = time_denoiser(denoiser, layers, repeats=1, warmup=0)
    assert image.shape == (*size, 3) and image.dtype == np.float32 and np.isfinite(image).all()
    assert seconds > 0
    mine = score(image, ref)
    assert all(math.isfinite(v) for v in mine.values())
    if min(size) >= 11:  # scikit-image refuses images smaller than the 11x11 window
        assert mine == pytest.approx(_independent_scores(image, ref), rel=1e-6)


def test_oidn_sanitizes_nonfinite_colour():
    layers = _synthetic_layers(16, 16)
    layers["diffuse"][2, 2, 0] = np.nan
    layers["specular"][4, 4, :] = -np.inf
    denoiser = OidnDenoiser()
    image = denoiser.denoise(layers)
    assert denoiser.last_sanitized == 4 and np.isfinite(image).all()


class _Shifted:
    """A real (if useless) denoiser: the noisy image rolled by one pixel, to exercise the interface."""

    name = "shifted"
    device = "cpu"

    def __init__(self, shape_error: bool = False):
        self.calls = 0
        self.shape_error = shape_error

    def denoise(self, layers):
        self.calls += 1
        image = np.roll(layers["diffuse"], 1, axis=1)
        return image[:-1] if self.shape_error else image

    def synchronize(self):
        pass


def test_time_denoiser_warms_up_then_times_repeats():
    layers = _synthetic_layers(8, 8)
    shifted = _Shifted()
    image, seconds = time_denoiser(shifted, layers, repeats=3, warmup=2)
    assert shifted.calls == 5 and seconds >= 0
    np.testing.assert_array_equal(image, np.roll(layers["diffuse"], 1, axis=1))
    with pytest.raises(ValueError, match="returned shape"):
        time_denoiser(_Shifted(shape_error=True), layers, repeats=1, warmup=0)


def test_evaluation_warms_each_denoiser_up_once_per_input_layout(renders, tmp_path):
    """Warm-up runs are paid at the first image of each layout (layer names and sizes), not at every
    image: every image still gets its `repeats` timed runs."""
    images = find_test_images(renders)
    layouts = {tuple(sorted((name, layer.shape) for name, layer in read_exr(t.noisy_path).items())) for t in images}
    shifted = _Shifted()
    evaluate(images, [shifted], tmp_path, progress=False, repeats=2, warmup=3)
    assert len(images) == 4 and 1 <= len(layouts) <= 2
    assert shifted.calls == 2 * len(images) + 3 * len(layouts)


def test_denoiser_names_are_checked(renders, tmp_path):
    images = find_test_images(renders)[:1]
    with pytest.raises(EvalError, match="unique"):
        evaluate(images, [NoisyInput(), NoisyInput()], tmp_path, progress=False)
    bad = _Shifted()
    bad.name = "path tracer"
    with pytest.raises(EvalError, match="reserved"):
        evaluate(images, [bad], tmp_path, progress=False)


def test_reference_floor_predicts_the_relmse_between_two_independent_references(variant, tmp_path):
    """Two references of the same scene rendered with other seeds differ by about the sum of their floors:
    the variance layers say how noisy a reference is (measured: within 10 % on these four scenes)."""
    from admc.common.metrics import reference_floor, relmse

    folders = []
    for seed in (0, 1):
        cfg = load_config(
            None,
            [
                f"run.workdir='{tmp_path / str(seed)}'",
                "run.scheduler=sync",
                f"render.seed={seed}",
                "render.resolution=[32, 32]",
                "render.spp=[4]",
                "render.reference_spp=64",
                "corpus.n_scenes=4",
            ],
        )
        folders.append(render_corpus(cfg, progress=False).renders_dir)
    for scene in sorted(p.name for p in folders[0].iterdir()):
        a, b = (read_exr(folder / scene / "reference.exr") for folder in folders)
        ra, rb = a["diffuse"] + a.get("specular", 0), b["diffuse"] + b.get("specular", 0)
        floors = [reference_floor(x["diffuse_var"] + x.get("specular_var", 0), rb) for x in (a, b)]
        assert relmse(ra, rb) == pytest.approx(sum(floors), rel=0.25), scene


def test_reference_floor_row_and_the_unbiased_relmse(renders, evaluated):
    from admc.common.metrics import reference_floor, ssim_floor

    result, out = evaluated
    floors, ssim_floors = {}, {}
    for folder in sorted(renders.iterdir()):
        ref = read_exr(folder / "reference.exr")
        radiance, variance = ref["diffuse"] + ref.get("specular", 0), ref["diffuse_var"] + ref.get("specular_var", 0)
        floors[folder.name] = reference_floor(variance, radiance)
        ssim_floors[folder.name] = ssim_floor(variance, radiance)
    assert all(0 < f < 0.1 for f in floors.values())
    assert all(0 < f < 1 for f in ssim_floors.values())
    for r in result.records + result.path_tracer:
        assert r.reference_floor == pytest.approx(floors[r.scene_id], rel=1e-12)
        assert r.relmse_minus_floor == pytest.approx(r.relmse - floors[r.scene_id], rel=1e-12, abs=1e-15)
        assert r.ssim_floor == ssim_floors[r.scene_id]  # seeded draws: the same value every time
    rows = _read_table(out / "table1.csv")
    for row in rows:
        assert float(row["reference_floor"]) == pytest.approx(np.mean(list(floors.values())), rel=1e-9)
        assert float(row["relmse_minus_floor_avg"]) == pytest.approx(
            float(row["relmse_avg"]) - float(row["reference_floor"]), rel=1e-9, abs=1e-12
        )
        assert float(row["ssim_floor"]) == pytest.approx(np.mean(list(ssim_floors.values())), rel=1e-9)
    md = (out / "table1.md").read_text()
    floor_rows = [line for line in md.splitlines() if "| reference floor |" in line]
    assert len(floor_rows) == 2
    cells = [c.strip() for c in floor_rows[0].split("|")]
    assert cells[3] == f"{np.mean(list(ssim_floors.values())):.4f}"  # under 1-SSIM Avg.
    assert cells[7] == f"{np.mean(list(floors.values())):.4f}"  # under relMSE Avg.
    assert "relMSE − floor" in md and "expected relMSE against the converged image" in md
    doc = json.loads((out / "results.json").read_text())
    assert doc["reference_floor"]["per_scene"] == pytest.approx(floors, rel=1e-12)
    assert doc["ssim_floor"]["per_scene"] == pytest.approx(ssim_floors, rel=1e-12)


def test_references_without_variance_layers_leave_the_floors_unknown(renders, tmp_path):
    """A reference rendered elsewhere has no variance layers: both floors are NaN in the records, null in
    results.json and empty in per_image.csv, and the table still builds."""
    scene = sorted(renders.iterdir())[0]
    copy = tmp_path / "renders" / scene.name
    shutil.copytree(scene, copy)
    layers = read_exr(copy / "reference.exr")
    write_exr(copy / "reference.exr", {name: layer for name, layer in layers.items() if not name.endswith("_var")})
    result = evaluate(
        find_test_images(tmp_path / "renders"), [NoisyInput()], tmp_path / "out", progress=False, repeats=1, warmup=0
    )
    for r in result.records + result.path_tracer:
        assert math.isnan(r.reference_floor) and math.isnan(r.ssim_floor) and math.isfinite(r.one_minus_ssim)
    doc = json.loads((tmp_path / "out" / "results.json").read_text())
    assert doc["reference_floor"]["per_scene"] == {scene.name: None}
    assert doc["ssim_floor"]["per_scene"] == {scene.name: None}
    per_image = _read_table(tmp_path / "out" / "per_image.csv")
    assert {row["ssim_floor"] for row in per_image} == {""} and {row["reference_floor"] for row in per_image} == {""}
    floor_rows = [
        line for line in (tmp_path / "out" / "table1.md").read_text().splitlines() if "| reference floor |" in line
    ]
    assert len(floor_rows) == 2 and all(line.count("| nan |") == 2 for line in floor_rows)


def test_noise_input_weights_name_a_test_render_without_variance(renders, tmp_path):
    """eval hands the renders' variance layers to model.noise_input weights; a test image without them
    is named with the layers it lacks (an EvalError: one line from `admc-pipe eval`, no traceback)."""
    from conftest import noise_input_weights

    from admc.model.inference.denoiser import load_denoiser
    from admc.model.inference.options import DenoiserOptions

    weights = noise_input_weights(tmp_path / "noise.pt")
    denoiser = load_denoiser(weights, DenoiserOptions(dtype=None))
    result = evaluate(
        find_test_images(renders), [NoisyInput(), denoiser], tmp_path / "out", progress=False, repeats=1, warmup=0
    )  # the renders carry diffuse_var and specular_var
    assert all(math.isfinite(r.relmse) for r in result.records)
    scene = sorted(renders.iterdir())[0]
    copy = tmp_path / "renders" / scene.name
    shutil.copytree(scene, copy)
    layers = read_exr(copy / "spp0002.exr")
    layers = {name: layer for name, layer in layers.items() if not name.endswith("_var")}
    write_exr(copy / "spp0002.exr", layers)
    with pytest.raises(
        EvalError,
        match=rf"{copy / 'spp0002.exr'}: lacks layer\(s\) diffuse_var(, specular_var)?, "
        rf"which admc's weights {weights} read",
    ):
        evaluate(
            find_test_images(tmp_path / "renders"),
            [NoisyInput(), denoiser],
            tmp_path / "out2",
            progress=False,
            repeats=1,
            warmup=0,
        )
