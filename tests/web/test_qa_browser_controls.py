"""QA pass on the lab pages in headless chromium: controls always show what the session runs, drive keys are
released wherever the focus went, the canvas fits a narrow window, and a closed connection is said, greys the
controls out and can be reopened."""

from __future__ import annotations

from typing import Any

import pytest

pytestmark = pytest.mark.browser

#: generous: a loaded machine is slow, never a failure (no timing asserts)
WAIT_MS = 120_000
FRAMES = "window.slamLab && window.slamLab.drawn > 3 && window.slamLab.hello !== null"
#: every text command the page sends, kept in the page (window.__sent)
RECORD_SENT = """(() => {
  window.__sent = [];
  const send = WebSocket.prototype.send;
  WebSocket.prototype.send = function (data) { window.__sent.push(String(data)); return send.call(this, data); };
})();"""


def open_page(page: Any, url: str) -> list[str]:
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    return errors


def test_a_refused_or_replaced_setting_shows_the_sessions_value_in_its_control(page: Any, lab_server: str) -> None:
    """The control a learner just used kept showing their choice while the session ran another: an estimator that
    falls back (lidar-lifelong in a world without walls -> dead-reckoning) or a refused number (seed 1.5)."""
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=20&seed=5")
    page.select_option("#ctl-scenario", "grid")
    page.wait_for_function("window.slamLab.values.scenario === 'grid'", timeout=WAIT_MS)
    page.focus("#ctl-estimator")  # as after picking from the list: the select keeps the focus
    s0 = page.evaluate("window.slamLab.states")
    page.select_option("#ctl-estimator", "lidar-lifelong")
    page.wait_for_function(f"window.slamLab.states > {s0}", timeout=WAIT_MS)
    assert page.evaluate("window.slamLab.values.estimator") == "dead-reckoning"
    assert page.evaluate("document.activeElement.id") == "ctl-estimator"
    assert page.input_value("#ctl-estimator") == "dead-reckoning"
    # an emptied number box is not a 0: nothing is sent and the box shows the seed again; then a refused value
    seed = page.locator("#ctl-seed")
    seed.fill("")
    seed.press("Tab")
    e0 = len(page.evaluate("window.slamLab.errors"))
    seed.fill("1.5")
    seed.press("Tab")
    page.wait_for_function(f"window.slamLab.errors.length > {e0}", timeout=WAIT_MS)
    assert "must be an integer" in page.evaluate("window.slamLab.errors").pop()
    assert page.evaluate("window.slamLab.values.seed") == 5  # replies come in order: an emptied box sent no 0
    assert seed.input_value() == "5"
    assert errors == []


def test_a_drive_key_released_after_the_focus_moved_to_a_control_is_released_on_the_server(
        page: Any, lab_server: str) -> None:
    """Held on the map, released on a checkbox (clicked meanwhile): the release was not sent, so the robot drove on
    by itself until it met a wall."""
    page.add_init_script(RECORD_SENT)
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=20&seed=3")
    page.locator("#world").click()
    page.keyboard.down("ArrowUp")
    page.focus("#ctl-paused")
    page.keyboard.up("ArrowUp")
    page.wait_for_function("window.__sent.some(m => { const c = JSON.parse(m); "
                           "return c.type === 'key' && c.key === 'ArrowUp' && c.down === false; })", timeout=WAIT_MS)
    assert errors == []


def test_a_narrow_window_shrinks_the_canvas_and_keeps_its_shape(page: Any, lab_server: str) -> None:
    page.set_viewport_size({"width": 600, "height": 800})
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=10")
    assert page.evaluate("document.documentElement.scrollWidth") <= 600
    w, h, bw, bh = page.evaluate("(() => { const c = document.getElementById('world'); "
                                 "return [c.clientWidth, c.clientHeight, c.width, c.height]; })()")
    assert w < bw and (bw, bh) == (760, 540)  # the drawing keeps its pixels; the element is scaled down
    assert h / w == pytest.approx(bh / bw, abs=0.02)
    page.set_viewport_size({"width": 1300, "height": 800})
    page.wait_for_function("document.getElementById('world').clientWidth === 760", timeout=WAIT_MS)
    assert errors == []


def test_a_closed_connection_is_shown_greys_the_controls_and_reconnect_starts_a_new_session(
        page: Any, lab_server: str) -> None:
    route: dict[str, Any] = {}

    def on_socket(ws: Any) -> None:
        route["page"] = ws
        ws.connect_to_server()

    page.route_web_socket("**/ws/problem*", on_socket)
    errors = open_page(page, f"{lab_server}/lab/problem?hz=20")
    route["page"].close()
    page.wait_for_function("window.slamLab.lost !== null", timeout=WAIT_MS)
    assert "connection to the lab server closed" in page.inner_text("#lost")
    assert page.evaluate("[...document.querySelectorAll('#controls input, #controls select, #controls button, "
                         "#check button')].every(e => e.disabled)")
    drawn = page.evaluate("window.slamLab.drawn")
    page.locator("#reconnect").click()
    page.wait_for_function(f"{FRAMES} && window.slamLab.drawn > {drawn + 3}", timeout=WAIT_MS)
    assert page.locator("#lost").count() == 0 and page.evaluate("window.slamLab.lost") is None
    assert not page.is_disabled("#act-reset") and not page.is_disabled("#check-choice-0")
    s0 = page.evaluate("window.slamLab.states")
    page.locator("#act-reset").click()  # the new session answers
    page.wait_for_function(f"window.slamLab.states > {s0}", timeout=WAIT_MS)
    assert errors == []
