"""Equal time between denoisers: each one's relMSE against another's at the same total time, interpolated on
the other's error-against-time curve, on the figures of a real `make demo` (issue 35), and in equal_time.md
and results.json."""

import json
import math
from pathlib import Path

import pytest

from admc.pipeline.evaluation.outputs import equal_time_between, error_at, write_outputs
from admc.pipeline.evaluation.records import PATH_TRACER, EvalResult, ImageRecord, aggregate

# spp -> (mean seconds, mean relMSE) from Table 1 of a fresh-clone `make demo` on the 2-core EPYC (issue 35)
OIDN = {16: (0.49, 0.00185), 64: (1.48, 0.00131)}
ADMC = {4: (0.94, 0.00327), 16: (1.21, 0.00176)}


def log_log(curve_a, curve_b, seconds):
    """The straight line in log time and log error through two points, at `seconds`."""
    (t0, e0), (t1, e1) = curve_a, curve_b
    return e0 * (e1 / e0) ** (math.log(seconds / t0) / math.log(t1 / t0))


def test_each_denoiser_is_compared_at_the_other_ones_error_for_the_same_time():
    rows = {(r["method"], r["spp"]): r for r in equal_time_between({"oidn": OIDN, "admc": ADMC})}
    assert set(rows) == {("oidn", 16), ("oidn", 64), ("admc", 4), ("admc", 16)}
    at_4 = rows[("admc", 4)]  # 0.94 s lies between OIDN's 16 spp (0.49 s) and 64 spp (1.48 s)
    assert at_4["other"] == "oidn"
    assert at_4["other_relmse"] == pytest.approx(log_log(OIDN[16], OIDN[64], 0.94), rel=1e-12)
    assert at_4["other_relmse"] == pytest.approx(0.001510, abs=1e-6)
    assert at_4["ratio"] == pytest.approx(0.00327 / 0.001510, rel=1e-3)  # admc 2.2x OIDN's error at equal time
    assert rows[("admc", 16)]["other_relmse"] == pytest.approx(log_log(OIDN[16], OIDN[64], 1.21), rel=1e-12)
    # admc's curve spans 0.94-1.21 s: OIDN's points at 0.49 s and 1.48 s lie outside it, no guess is made
    assert rows[("oidn", 16)]["other_relmse"] is None and rows[("oidn", 64)]["ratio"] is None


def test_error_at_a_curve_point_is_that_point_and_outside_is_none():
    assert error_at(OIDN, 0.49) == pytest.approx(0.00185, rel=1e-12)
    assert error_at(OIDN, 1.48) == pytest.approx(0.00131, rel=1e-12)
    assert error_at(OIDN, 0.48) is None and error_at(OIDN, 1.5) is None


def _records(method, curve, render):
    """Two scenes per spp whose means are `curve`'s points (±10% around them), rendered in `render` seconds."""
    return [
        ImageRecord(
            scene,
            spp,
            method,
            "cpu",
            0.1,
            30.0,
            relmse * factor,
            0.2,
            0,
            render[spp],
            seconds - render[spp],
            Path(f"/out/images/{scene}_{spp}_{method}.exr"),
        )
        for spp, (seconds, relmse) in curve.items()
        for scene, factor in (("a", 0.9), ("b", 1.1))
    ]


def test_the_table_is_written_next_to_the_comparison_with_the_raw_path_tracer(tmp_path):
    render = {4: 0.20, 16: 0.40, 64: 1.30}
    raw = {4: (0.20, 0.0975), 16: (0.40, 0.0296), 64: (1.30, 0.0098)}
    oidn = {4: (0.29, 0.0079), **OIDN}
    records = _records("oidn", oidn, render) + _records("admc", ADMC, render)
    devices = {"oidn": "cpu", "admc": "cpu"}
    result = EvalResult(
        table=aggregate(records, devices),
        records=records,
        path_tracer=_records(PATH_TRACER, raw, render),
        scenes=[],
        devices=devices,
        files={},
    )
    for r in result.records + result.path_tracer:
        object.__setattr__(r, "image", tmp_path / "images" / r.image.name)
    write_outputs(result, tmp_path, repeats=1, warmup=0)
    text = (tmp_path / "equal_time.md").read_text()
    raw_part, between_part = text.split("# Equal time: denoiser against denoiser")
    assert "against the raw path tracer" in raw_part
    expected = log_log(OIDN[16], OIDN[64], 0.94)
    assert f"| admc | 4 | 0.94 | 0.00327 | oidn | {expected:.4g} | {0.00327 / expected:.3f} |" in between_part
    assert "| oidn | 64 | 1.48 | 0.00131 | admc | outside | – |" in between_part
    doc = json.loads((tmp_path / "results.json").read_text())
    assert len(doc["equal_time_between_denoisers"]) == 3 + 2
