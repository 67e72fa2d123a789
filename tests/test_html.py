"""The HTML evaluation report: built from real arrays and PNG plots, then opened in a real headless
Chromium spoken to over the DevTools protocol on a pipe (stdlib only): images decode, no console
errors or exceptions, no network requests, the synchronised zoom follows real mouse events, and a
screenshot renders. Browser tests skip when Chromium is absent (CI installs Debian's chromium).
"""

from __future__ import annotations

import base64
import io
import json
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from PIL import Image

from admc.pipeline.evaluation.html import MAX_EMBED, ReportImage, embed_size, report_group, table_html, write_report
from admc.pipeline.evaluation.table1 import Cell, Note, Table1

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the headless backend)

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="the browser tests need Chromium (apt-get install -y chromium, as .ci/run does)"
)

TABLE = Table1(
    head=["spp", "denoiser", "1-SSIM", "PSNR", "relMSE"],
    rows=[
        [Cell("4"), Cell("noisy"), Cell("0.41"), Cell("21.3"), Cell("0.0975")],
        [Cell(""), Cell("ours"), Cell("0.05", True), Cell("33.9", True), Cell("0.0079", True)],
    ],
    notes=[Note("", "Best average in bold."), Note("Devices:", "noisy: cpu; ours: <cpu>")],
)


# ---------------------------------------------------------------- inputs


def _split_scene(scene_id: str, h: int, w: int, spp: int = 4, seed: int = 0) -> ReportImage:
    """Left half red, right half blue, green rising with the row: colours tell where the zoom looks."""
    rng = np.random.default_rng(seed)
    ref = np.zeros((h, w, 3), np.float32)
    ref[:, : w // 2, 0] = 0.8
    ref[:, w // 2 :, 2] = 0.8
    ref[..., 1] = 0.2 * np.arange(h)[:, None] / h
    noisy = (ref * rng.exponential(1.0, ref.shape)).astype(np.float32)
    ours = (ref + rng.normal(0.0, 0.01, ref.shape)).astype(np.float32)
    metrics = {
        "noisy": {"1-SSIM": 0.41, "PSNR": 21.3, "relMSE": 0.0975},
        "ours": {"1-SSIM": 0.05, "PSNR": 33.9, "relMSE": 0.0079},
    }
    return ReportImage(scene_id, spp, ref, {"noisy": noisy, "ours": ours}, metrics)


def _plot(path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(4, 3), dpi=60)
    ax.loglog([1, 4, 16, 64], [0.3, 0.1, 0.03, 0.01], marker="o")
    ax.set_xlabel("time [s]")
    fig.savefig(path)
    plt.close(fig)
    return path


def _report(tmp_path: Path, images: list[ReportImage], notes: tuple[str, ...] = ()) -> Path:
    return write_report(
        tmp_path / "report",
        title="admc evaluation <test>",
        table=TABLE,
        metric_definitions={"relMSE": "mean (x - ref)^2 / (ref^2 + 0.01)", "PSNR": "dB on 8 bit"},
        plots=[_plot(tmp_path / "error_vs_time.png")],
        groups=[report_group(i) for i in images],
        device="cpu (test)",
        notes=list(notes),
    )


def _extreme_images() -> list[ReportImage]:
    nan = _split_scene("nan-output", 24, 32)
    nan.outputs["ours"][4:8, 4:8] = np.nan
    nan.outputs["ours"][20, 30] = np.inf
    black = _split_scene("black-reference", 16, 16)
    black.reference[:] = 0.0
    return [nan, black, _split_scene("one-pixel", 1, 1), _split_scene("thin", 37, 4000), _split_scene("tall", 900, 5)]


def _data_uris(page: str) -> list[str]:
    return [chunk.split('"', 1)[0] for chunk in page.split('src="data:image/png;base64,')[1:]]


def _decode(uri: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(uri))).convert("RGB"))


# ---------------------------------------------------------------- Python side, no browser


def test_table_cells_bold_notes_and_escaping():
    """The page renders the Table1 object itself: its cells, the best ones <strong>, its notes, escaped."""
    out = table_html(TABLE)
    assert out.count("<tr>") == 3 and out.count("<th>") == 5
    assert "<th>denoiser</th>" in out and "<td>0.41</td>" in out and "<td></td>" in out
    assert "<td><strong>33.9</strong></td>" in out and "<td><strong>0.0079</strong></td>" in out
    assert "<p>Best average in bold.</p>" in out
    assert "<p><strong>Devices:</strong> noisy: cpu; ours: &lt;cpu&gt;</p>" in out
    assert TABLE.markdown().splitlines()[3] == "|  | ours | **0.05** | **33.9** | **0.0079** |"


def test_table1_comes_first_and_definitions_follow_the_plots(tmp_path):
    page = _report(tmp_path, [_split_scene("s", 8, 8)]).read_text()
    headings = [chunk.split("</h2>", 1)[0] for chunk in page.split("<h2>")[1:]]
    assert headings == ["Table 1", "Plots", "Metrics", "Notes", "Images"]


def test_bad_inputs_raise_clear_errors(tmp_path):
    item = _split_scene("s", 8, 8)
    item.outputs["ours"] = item.outputs["ours"][:4]
    with pytest.raises(ValueError, match=r"'s' @ 4 spp: output 'ours' has shape \(4, 8, 3\), reference \(8, 8, 3\)"):
        _report(tmp_path, [item])
    not_png = tmp_path / "plot.png"
    not_png.write_text("nope")
    kwargs = dict(title="t", table=Table1([], [], []), metric_definitions={}, groups=[], device="cpu")
    with pytest.raises(ValueError, match="plot.png: not a PNG file"):
        write_report(tmp_path / "r", plots=[not_png], **kwargs)
    with pytest.raises(ValueError, match="missing.png: no such file"):
        write_report(tmp_path / "r", plots=[tmp_path / "missing.png"], **kwargs)


def test_embedded_pixels_tonemap_heatmap_nan_and_downscale(tmp_path):
    images = _extreme_images()
    page = _report(tmp_path, images).read_text()
    assert "http://" not in page and "https://" not in page
    uris = _data_uris(page)
    # per group: noisy, ours, reference, then heat noisy, heat ours, legend bar; plus the plot first
    assert len(uris) == 1 + 6 * len(images)
    nan_group = [_decode(u) for u in uris[1:7]]
    ours, reference, heat_ours = nan_group[1], nan_group[2], nan_group[4]
    assert ours.shape == (24, 32, 3)
    assert (ours[5, 5] == (255, 0, 255)).all() and (ours[20, 30] == (255, 0, 255)).all()
    assert (heat_ours[5, 5] == (255, 0, 255)).all()
    # red 0.8 -> round(255 * 0.8^(1/2.2)) = 230
    assert tuple(reference[0, 0]) == (230, 0, 0) and tuple(reference[0, -1]) == (0, 0, 230)
    # heat map colour = inferno at (log10(mean_c (x - ref)^2 / (ref^2 + 0.01)) + 5) / 7, for both outputs
    for name, heat in (("noisy", nan_group[3]), ("ours", heat_ours)):
        x, ref = images[0].outputs[name][12, 2].astype(np.float64), images[0].reference[12, 2]
        level = (np.clip(np.log10(np.mean((x - ref) ** 2 / (ref**2 + 0.01))), -5, 2) + 5) / 7
        expected = np.asarray(matplotlib.colormaps["inferno"](level)[:3]) * 255
        assert np.abs(heat[12, 2] - expected).max() <= 3, name
    assert "nan-output @ 4 spp: ours has 17 NaN/Inf pixels, shown magenta." in page
    thin = _decode(uris[1 + 6 * 3 + 2])
    assert (thin.shape[1], thin.shape[0]) == embed_size((37, 4000)) == (MAX_EMBED[0], 12)
    assert "4000x37, embedded box-downscaled to 1280x12" in page
    assert _decode(uris[1 + 6 * 2]).shape == (1, 1, 3)


# ---------------------------------------------------------------- the browser


class Chromium:
    """Headless Chromium driven over --remote-debugging-pipe: JSON messages, NUL-terminated, fds 3 and 4."""

    def __init__(self, profile: Path):
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()

        def wire_fds():  # runs in the child before exec: the pipe protocol expects exactly fds 3 and 4
            os.dup2(to_browser_r, 3)
            os.dup2(from_browser_w, 4)

        self.process = subprocess.Popen(
            [
                CHROMIUM,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--hide-scrollbars",
                f"--user-data-dir={profile}",
                "--remote-debugging-pipe",
                "about:blank",
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=wire_fds,
            pass_fds=(3, 4),
        )
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict] = []

    def close(self) -> None:
        self.process.kill()
        self.process.wait()
        os.close(self._to_browser)
        os.close(self._from_browser)

    def _receive(self, deadline: float) -> dict:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._from_browser], [], [], left)[0]:
                raise TimeoutError("no DevTools message from Chromium in time")
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise RuntimeError("Chromium closed the DevTools pipe")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def send(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 30.0) -> dict:
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            reply = self._receive(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]
            self.events.append(reply)

    def wait_event(self, method: str, session: str, timeout: float = 30.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            for event in self.events:
                if event.get("method") == method and event.get("sessionId") == session:
                    return event
            self.events.append(self._receive(deadline))


class Page:
    """One tab: loads a file, records console errors, exceptions and network requests, runs JS, clicks."""

    def __init__(self, browser: Chromium, path: Path, size: tuple[int, int] = (1400, 1000)):
        self.browser = browser
        target = browser.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = browser.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.send(f"{domain}.enable")
        self.send(
            "Emulation.setDeviceMetricsOverride",
            {"width": size[0], "height": size[1], "deviceScaleFactor": 1, "mobile": False},
        )
        self.send("Page.navigate", {"url": path.resolve().as_uri()})
        browser.wait_event("Page.loadEventFired", self.session)

    def send(self, method: str, params: dict | None = None) -> dict:
        return self.browser.send(method, params, self.session)

    def js(self, expression: str):
        result = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in result:
            raise RuntimeError(f"page JS failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_ready(self, timeout: float = 30.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ready = self.js("document.body.dataset.ready || ''")
            if ready:
                return ready
            time.sleep(0.05)
        raise TimeoutError("the page never set body[data-ready]")

    def mouse(self, kind: str, x: float, y: float) -> None:
        params = {"type": kind, "x": x, "y": y, "button": "left" if kind != "mouseMoved" else "none"}
        if kind != "mouseMoved":
            params["clickCount"] = 1
        self.send("Input.dispatchMouseEvent", params)

    def click(self, x: float, y: float) -> None:
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.mouse(kind, x, y)

    def errors(self) -> list[str]:
        """Console errors/asserts, uncaught exceptions and error log entries of this tab so far."""
        found = []
        for event in self.browser.events:
            if event.get("sessionId") != self.session:
                continue
            method, params = event.get("method"), event.get("params", {})
            if method == "Runtime.consoleAPICalled" and params["type"] in ("error", "assert"):
                found.append("console: " + " ".join(str(a.get("value", a.get("description"))) for a in params["args"]))
            elif method == "Runtime.exceptionThrown":
                details = params["exceptionDetails"]
                found.append("exception: " + details.get("exception", {}).get("description", details["text"]))
            elif method == "Log.entryAdded" and params["entry"]["level"] == "error":
                found.append("log: " + params["entry"]["text"])
        return found

    def requested_urls(self) -> list[str]:
        return [
            e["params"]["request"]["url"]
            for e in self.browser.events
            if e.get("sessionId") == self.session and e.get("method") == "Network.requestWillBeSent"
        ]

    def screenshot(self, path: Path) -> Path:
        path.write_bytes(base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"]))
        return path


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    chromium = Chromium(tmp_path_factory.mktemp("chromium-profile"))
    chromium.send("Browser.getVersion")  # fails fast when the browser did not start
    yield chromium
    chromium.close()


@needs_chromium
def test_report_loads_decodes_every_image_without_errors_or_network(tmp_path, browser):
    images = [_split_scene("cornell", 48, 64)] + _extreme_images()
    report = _report(tmp_path, images, notes=("trained on the default corpus",))
    page = Page(browser, report)
    expected = 1 + 6 * len(images)
    assert page.wait_ready() == f"ok {expected}"
    assert page.js("Array.from(document.images).filter(i => i.naturalWidth > 0).length") == expected
    assert page.errors() == []
    assert {url.split(":", 1)[0] for url in page.requested_urls()} <= {"file", "data"}
    assert page.js("document.querySelectorAll('table strong').length") == 3
    assert page.js("document.querySelectorAll('.group').length") == len(images)
    assert "ours has 17 NaN/Inf pixels" in page.js("document.body.innerText")
    # the screenshot: header, Table 1 and plot on top; scroll to the first image group for a second one
    top = page.screenshot(tmp_path / "report_top.png")
    page.js("document.getElementById('group-0').scrollIntoView()")
    images_shot = page.screenshot(tmp_path / "report_images.png")
    for shot in (top, images_shot):
        pixels = np.asarray(Image.open(shot).convert("RGB"))
        assert pixels.shape == (1000, 1400, 3)
        assert pixels.std() > 10  # not a blank page
    if os.environ.get("ADMC_REPORT_SCREENSHOT_DIR"):  # for a person who wants to look at the page
        for shot in (top, images_shot):
            shutil.copy(shot, Path(os.environ["ADMC_REPORT_SCREENSHOT_DIR"]) / shot.name)


@needs_chromium
def test_zoom_follows_hover_pins_on_click_and_is_synchronised(tmp_path, browser):
    report = _report(tmp_path, [_split_scene("split", 48, 64), _split_scene("other", 48, 64, seed=1)])
    page = Page(browser, report)
    assert page.wait_ready() == "ok 13"
    embedded_reference = _decode(_data_uris(report.read_text())[3])  # after the plot, noisy and ours
    page.js("document.getElementById('group-0').scrollIntoView()")
    box = page.js(
        "(() => { const r = document.querySelector('#group-0 .fig:last-child img').getBoundingClientRect();"
        " return [r.left, r.top, r.width, r.height]; })()"
    )
    left, top, width, height = box

    def point(px: int, py: int) -> tuple[float, float]:  # screen position of source pixel (px, py)
        return left + (px + 0.5) * width / 64, top + (py + 0.5) * height / 48

    state = """(() => Array.from(document.querySelectorAll('#group-GROUP canvas.zoom')).map(c => {
        const p = c.getContext('2d').getImageData(80, 80, 1, 1).data;
        return [c.hidden, Number(c.dataset.x), Number(c.dataset.y), p[0], p[1], p[2]]; }))()"""
    assert all(hidden for hidden, *_ in page.js(state.replace("GROUP", "0")))

    page.mouse("mouseMoved", *point(10, 20))  # hover on the red half
    hovered = page.js(state.replace("GROUP", "0"))
    assert len(hovered) == 5  # noisy, ours, reference, 2 heat maps
    assert [c[:3] for c in hovered] == [[False, 10, 20]] * 5
    ours, reference = hovered[1], hovered[2]
    assert reference[3:] == embedded_reference[20, 10].tolist() and reference[3] == 230 and reference[5] == 0
    assert ours[3] > 200 and ours[5] < 30
    assert page.js("document.querySelector('#group-0 .marker').hidden") is False

    page.click(*point(50, 5))  # pin on the blue half
    page.mouse("mouseMoved", *point(3, 3))  # moving away keeps the pinned region
    pinned = page.js(state.replace("GROUP", "0"))
    assert [c[:3] for c in pinned] == [[False, 50, 5]] * 5
    assert pinned[2][3:] == embedded_reference[5, 50].tolist() and pinned[2][5] == 230
    assert all(hidden for hidden, *_ in page.js(state.replace("GROUP", "1")))  # other scenes untouched

    page.js("const s = document.getElementById('zoom-level'); s.value = '32'; s.dispatchEvent(new Event('change'))")
    marker = page.js(
        "(() => { const m = document.querySelector('#group-0 .marker').style; return [m.width, m.height]; })()"
    )
    assert [float(m.rstrip("%")) for m in marker] == pytest.approx(
        [100 * 5 / 64, 100 * 5 / 48], abs=1e-3
    )  # 160 px / 32x

    page.click(*point(50, 5))  # unpin: hover takes over again
    page.mouse("mouseMoved", *point(40, 30))
    unpinned = page.js(state.replace("GROUP", "0"))
    assert [c[:3] for c in unpinned] == [[False, 40, 30]] * 5
    assert unpinned[2][3:] == embedded_reference[30, 40].tolist()
    assert page.errors() == []


@needs_chromium
def test_harness_catches_page_errors_and_undecodable_images(tmp_path, browser):
    """The checks above can fail: a thrown error, a console.error and a broken image are all seen."""
    report = _report(tmp_path, [_split_scene("s", 8, 8)])
    broken = report.read_text().replace(
        "</body>",
        '<img src="data:image/png;base64,bm90IGEgcG5n"><script>console.error("boom");'
        "undefinedFunction();</script></body>",
    )
    bad = report.with_name("broken.html")
    bad.write_text(broken)
    page = Page(browser, bad)
    assert page.wait_ready() == "failed 1/8"
    errors = page.errors()
    assert "console: boom" in errors
    assert any(e.startswith("exception: ReferenceError: undefinedFunction is not defined") for e in errors)
    assert "console: 1 of 8 images failed to decode" in errors


def test_a_run_without_chromium_names_the_skipped_browser_tests_in_one_line(tmp_path):
    """`make test` on a machine without Chromium passes, and says which tests it did not run and why."""
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            f"{__file__}::test_report_loads_decodes_every_image_without_errors_or_network",
            f"{__file__}::test_harness_catches_page_errors_and_undecodable_images",
        ],
        env=dict(os.environ, PATH=str(tmp_path)),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert (
        "skipped 2 (test_report_loads_decodes_every_image_without_errors_or_network, "
        "test_harness_catches_page_errors_and_undecodable_images): the browser tests need Chromium "
        "(apt-get install -y chromium, as .ci/run does)"
    ) in out.stdout.splitlines(), out.stdout
