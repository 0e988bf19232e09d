"""The dashboard in real headless Debian Chromium, driven by Playwright."""

from __future__ import annotations

import contextlib
import re
import shutil
from pathlib import Path

import pytest

from imunoise.analysis.terms import term_names
from imunoise.live.service import LiveService
from imunoise.web.app import create_app
from tests.live_helpers import SyntheticImu, running_server

try:
    from playwright.sync_api import TimeoutError as PlaywrightTimeout
except ImportError:  # pragma: no cover - playwright is in the test extra
    PlaywrightTimeout = TimeoutError

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).exists() and shutil.which("chromium") is None,
    reason="Debian chromium is not installed (apt-get install -y chromium)")


@pytest.fixture(scope="module")
def url():
    svc = LiveService(SyntheticImu(block=1000, n_blocks=300), realtime=False).start()
    assert svc.wait(60)
    svc.stop()
    with running_server(create_app(svc)) as base:
        yield base


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM if Path(CHROMIUM).exists()
                              else shutil.which("chromium"), args=ARGS)
        yield b
        b.close()


@pytest.fixture()
def page(browser):
    page = browser.new_page(viewport={"width": 1400, "height": 1600})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.errors = errors
    yield page
    page.close()


@contextlib.contextmanager
def screenshot_on_failure(page, tmp_path: Path, name: str):
    """Re-raise a failed check or wait with the path of a screenshot of the page."""
    try:
        yield
    except (AssertionError, PlaywrightTimeout) as exc:
        shot = tmp_path / f"{name}.png"
        try:
            page.screenshot(path=str(shot), full_page=True, timeout=5000)
            where = f"screenshot: {shot}"
        except PlaywrightTimeout:
            where = "no screenshot: the page is unresponsive"
        raise AssertionError(f"{exc} ({where})") from exc


def test_dashboard_loads_and_plots_render_with_data(page, url, tmp_path) -> None:
    with screenshot_on_failure(page, tmp_path, "dashboard"):
        _check_dashboard(page, url)


def _check_dashboard(page, url: str) -> None:
    page.goto(url + "/")
    page.wait_for_function("Number(document.body.dataset.renders || 0) >= 1", timeout=15000)
    for plot_id, least in (("allan-plot", 12), ("z-plot", 12), ("psd-plot", 100),
                           ("history-plot", 1)):
        el = page.locator(f"#{plot_id}")
        assert el.locator("canvas").count() == 1, f"{plot_id} has no canvas"
        assert int(el.get_attribute("data-points") or 0) >= least, f"{plot_id} is empty"
    _check_log_axis_labels(page)
    # The error history's axis counts seconds since the first fit, not calendar dates: with
    # one point it spans a second either side of 0, with several their elapsed seconds.
    x = page.evaluate("[state.plots['history-plot'].scales.x.min, "
                      "state.plots['history-plot'].scales.x.max, "
                      "state.plots['history-plot'].axes[0]._values || []]")
    assert -1.0 <= x[0] <= 0.0 < x[1] < 3600.0, x
    assert not any(re.search(r"20\d\d|Jan|May", str(v)) for v in x[2]), x[2]
    # The default model misses gyro_x's sinusoid: the z strip marks failures.
    assert int(page.locator("#z-plot").get_attribute("data-failures")) > 0
    rows = page.locator("#coefficients tbody tr")
    assert rows.count() == 3
    assert "deg/sqrt(h)" in rows.first.inner_text()
    # Every term not in the model can be added from the model editor.
    live_terms = term_names(live=True)
    assert page.locator("#model-editor button.add-any").count() == len(live_terms) - 3
    assert "samples" in page.locator("#status").inner_text()
    # the error's other parts beside the Allan one: the PSD part as /coefficients gives it,
    # the hold-out and time-domain parts with the reason they are not computed live
    # (the next refresh, should this one have asked before the PSD had its first estimate)
    page.wait_for_function(
        "/^PSD deviance\\/bin \\d/.test(document.getElementById('error-parts').textContent)",
        timeout=15000)
    parts = page.locator("#error-parts").inner_text()
    assert re.search(r"^PSD deviance/bin \d", parts) and "bins outside 95 %" in parts, parts
    assert ("hold-out χ²/dof n/a (not computed by the live service: imunoise fit on the "
            "recording reports it)") in parts, parts
    assert "time domain max|z| n/a (not computed by the live service" in parts, parts
    assert page.errors == [], f"console errors {page.errors}"


DECADE = re.compile(r"^(1|10|10⁻?[¹²³⁴⁵⁶⁷⁸⁹][⁰¹²³⁴⁵⁶⁷⁸⁹]*)$")


def _check_log_axis_labels(page) -> None:
    """Log axes label decades only (10⁻³, 10⁻², 1, 10 ...); minor ticks carry no text."""
    for plot_id, axes in (("allan-plot", (0, 1)), ("psd-plot", (0, 1)), ("z-plot", (0,))):
        ticks = page.evaluate(f"state.plots['{plot_id}'].axes.map((a) => a._values || [])")
        for i in axes:
            labels = ticks[i]
            shown = [t for t in labels if t]
            assert len(shown) >= 2, f"{plot_id} axis {i}: too few decade labels {labels}"
            assert all(DECADE.match(t) for t in shown), f"{plot_id} axis {i}: {labels}"
            assert len(labels) > len(shown), f"{plot_id} axis {i}: no unlabelled minor ticks"


def test_clicking_add_changes_the_model_and_the_error_falls(page, url, tmp_path) -> None:
    with screenshot_on_failure(page, tmp_path, "add-term"):
        _check_add(page, url)


def _check_add(page, url: str) -> None:
    page.goto(url + "/?channel=gyro_x")
    page.wait_for_function("Number(document.body.dataset.renders || 0) >= 1", timeout=15000)
    before = float(page.locator("#error-value").get_attribute("data-value"))
    renders = int(page.evaluate("document.body.dataset.renders"))
    top = page.locator("#suggestions button.add-term").first  # the diagnosis's best
    assert top.get_attribute("data-term") == "sinusoid"
    top.click()
    page.wait_for_function(f"Number(document.body.dataset.renders) > {renders}", timeout=15000)
    page.wait_for_function(
        f"Number(document.getElementById('error-value').dataset.value) < {before}",
        timeout=15000)
    after = float(page.locator("#error-value").get_attribute("data-value"))
    assert after < before / 10, f"error {before} -> {after}"
    # A refresh already under way when the model changed may draw a diagnosis and history
    # asked for before the change; the refresh queued behind it draws the new ones.
    page.wait_for_function(
        "document.querySelectorAll(\"button[data-term='sinusoid']:not(.remove-term)\")"
        ".length === 0 && /^rev 1/.test(document.querySelector('#history li').textContent)",
        timeout=15000)
    assert page.locator("#model-terms .term", has_text="sinusoid").count() == 1
    assert "→" in page.locator("#action-msg").inner_text()
    history = page.locator("#history li").all_inner_texts()
    assert history[0].startswith("rev 1") and "sinusoid" in history[0]
    # both parts of the error, each entry: the line lowers the PSD part as well
    parts = [re.search(r"Allan χ²/dof ([-+0-9.e]+) · PSD deviance/bin ([-+0-9.e]+)", h)
             for h in history]
    assert all(parts), history
    first_rev0 = next(p for h, p in zip(history, parts, strict=True) if h.startswith("rev 0"))
    assert float(parts[0].group(2)) < float(first_rev0.group(2)), history
    assert page.evaluate("state.plots['history-plot'].series.map((s) => s.label)") == \
        ["s since the first fit", "Allan χ²/dof", "PSD deviance/bin"]
    # Any term can be added from the model editor, and removed with its x.
    page.locator("#model-editor button.add-any[data-term='rate_ramp']").click()
    page.wait_for_function("document.querySelector(\"#model-terms button[data-term="
                           "'rate_ramp']\") !== null", timeout=15000)
    assert page.locator("#model-editor button.add-any[data-term='rate_ramp']").count() == 0
    page.locator("#model-terms button.remove-term[data-term='rate_ramp']").click()
    page.wait_for_function("document.querySelector(\"#model-terms button[data-term="
                           "'rate_ramp']\") === null", timeout=15000)
    assert float(page.locator("#error-value").get_attribute("data-value")) == \
        pytest.approx(after, rel=1e-9)  # back to the same model on the same samples
    assert page.errors == [], f"console errors {page.errors}"


def test_a_young_record_with_short_tau_range_renders_without_errors(browser, tmp_path) -> None:
    """Less than two decades of tau and no PSD yet: the log axes must still draw."""
    svc = LiveService(SyntheticImu(fs_hz=102.4, block=100, n_blocks=6), realtime=False).start()
    assert svc.wait(30)
    # the replay's last analysis (a full fit and a diagnosis of each of the six channels,
    # about 4.5 s of CPU each on a 600-sample record) must end before the worker closes:
    # with stop's default 10 s the diagnosis of gyro_y, the second, was sometimes cut off
    # and the page then waited for it for good
    svc.stop(timeout=120)
    page = browser.new_page(viewport={"width": 1200, "height": 1400})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    with running_server(create_app(svc)) as base, \
            screenshot_on_failure(page, tmp_path, "young-record"):
        page.goto(base + "/?channel=gyro_y")
        page.wait_for_function("Number(document.body.dataset.renders || 0) >= 1", timeout=15000)
        # 600 samples: octave taus m = 1 .. 128 (up to a quarter of the record)
        assert int(page.locator("#allan-plot").get_attribute("data-points")) == 8
        page.wait_for_timeout(300)  # let the plots draw
        assert page.evaluate("1 + 1") == 2  # the page is responsive, not stuck drawing
        # the model is right: suggestions, none significant
        page.wait_for_selector("#suggestions button.add-term", timeout=15000)
        assert page.locator("#suggestions .sig").count() == 0
        assert errors == [], errors
    page.close()
