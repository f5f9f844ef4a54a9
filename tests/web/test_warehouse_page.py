"""The warehouse design-challenge page in headless chromium: relocalisation hypotheses then a decision, the static
layer drawn, the controls (start mode, floor markers, forklift count) applied by the server."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from slam2d.web.sessions.warehouse import max_forklifts

pytestmark = pytest.mark.browser

FRAMES = "window.slamLab && window.slamLab.drawn > 3 && window.slamLab.hello !== null"


def open_page(page: Any, url: str) -> list[str]:
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    return errors


def set_control(page: Any, name: str, value: Any) -> None:
    page.eval_on_selector(f"#ctl-{name}", "(e, v) => { if (e.type === 'checkbox') e.checked = v; else e.value = v; "
                                          "e.dispatchEvent(new Event('change')); }", value)

PIXELS = """() => {
  const g = document.getElementById('world').getContext('2d'), s = window.slamLab.gridSample;
  const lum = ([x, y]) => { const d = g.getImageData(x, y, 1, 1).data; return (d[0] + d[1] + d[2]) / 3; };
  return { occ: s.occ.map(lum), free: s.free.map(lum) };
}"""


def test_warehouse_relocalises_and_draws_the_static_layer(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/warehouse?hz=15")
    page.wait_for_function(FRAMES, timeout=50_000)  # the first session builds the saved map (seconds)
    # relocalisation: several hypotheses while undecided ...
    page.wait_for_function("window.slamLab.counters.hypotheses > 1", timeout=20_000)
    assert page.evaluate("window.slamLab.relocText").startswith("undecided")
    assert page.evaluate("window.slamLab.sections.HYPO[0]") > 1
    # ... then either one accepted, or honestly still undecided after a while of motion
    page.wait_for_function("window.slamLab.counters.accepted_step >= 0 || window.slamLab.counters.time_s > 15",
                           timeout=40_000)
    c = page.evaluate("window.slamLab.counters")
    text = page.evaluate("window.slamLab.relocText")
    if c["accepted_step"] is not None and c["accepted_step"] == c["accepted_step"]:
        assert text.startswith("relocalised")
        assert "HYPO" not in page.evaluate("window.slamLab.sections")
    else:
        assert text.startswith("undecided")
    # the static layer is on the canvas: occupied cells dark, free cells light (sampled pixels)
    page.wait_for_function("window.slamLab.gridSample && window.slamLab.gridSample.occ.length > 50", timeout=5000)
    px = page.evaluate(PIXELS)
    dark = sum(v < 100 for v in px["occ"]) / len(px["occ"])
    light = sum(v > 200 for v in px["free"]) / len(px["free"])
    assert dark > 0.8 and light > 0.8, (dark, light)
    page.screenshot(path=str(artifacts / "warehouse.png"), full_page=True)
    assert errors == []


def test_warehouse_controls(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/warehouse?hz=10&seed=1")
    page.wait_for_function(FRAMES, timeout=50_000)
    # cold start: no relocaliser, the estimator maps from the true start
    page.locator("#ctl-start").select_option("cold start")
    page.wait_for_function("window.slamLab.values.start === 'cold start' && "
                           "window.slamLab.relocText.startsWith('cold start')", timeout=30_000)
    page.wait_for_function("window.slamLab.counters.keyframes >= 1", timeout=30_000)
    # floor markers off
    set_control(page, "floor_markers", False)
    page.wait_for_function("window.slamLab.values.floor_markers === false", timeout=30_000)
    # forklifts: a count in the validated range is applied, one above it is refused by the server
    hi = max_forklifts()
    assert hi >= 3
    set_control(page, "forklifts", 3)
    page.wait_for_function("window.slamLab.counters.forklifts === 3", timeout=30_000)
    page.evaluate(f"window.slamLab.send({{type: 'param', name: 'forklifts', value: {hi + 1}}})")
    page.wait_for_function("window.slamLab.errors.some(e => e.includes('forklifts'))", timeout=10_000)
    assert page.evaluate("window.slamLab.values.forklifts") == 3
    # back to the saved map
    page.locator("#ctl-start").select_option("saved map")
    page.wait_for_function("window.slamLab.relocText.startsWith('undecided') || "
                           "window.slamLab.relocText.startsWith('relocalised')", timeout=30_000)
    assert errors == []
