"""Every lab page in headless chromium: loads without console errors, draws frames, controls change the numbers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from slam2d.lab.registry import estimator_names
from slam2d.web.checks import CHECKS
from slam2d.web.pages import PAGES
from slam2d.web.tasks import TASKS

pytestmark = pytest.mark.browser

#: how long a test waits for the page: generous (a loaded machine is slow, never a failure; no timing asserts)
WAIT_MS = 120_000
FRAMES = "window.slamLab && window.slamLab.drawn > 3 && window.slamLab.hello !== null"


def open_page(page: Any, url: str) -> list[str]:
    """Go to ``url``, collect console errors and page errors, wait until frames are being drawn."""
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    return errors


def wait_or_explain(page: Any, condition_js: str) -> None:
    """Wait for ``condition_js``; on a timeout, fail with what the page knew (connection, errors, last feedback), so
    that a failure seen once under load says where it stopped."""
    try:
        page.wait_for_function(condition_js, timeout=WAIT_MS)
    except Exception as e:
        state = page.evaluate("({connected: window.slamLab.connected, errors: window.slamLab.errors, "
                              "feedback: window.slamLab.feedback, states: window.slamLab.states, "
                              "drawn: window.slamLab.drawn, status: document.getElementById('status')?.textContent})")
        raise AssertionError(f"waited {WAIT_MS / 1000:g} s for {condition_js}; the page: {state}") from e


def next_frames(page: Any, n: int = 3) -> None:
    """Wait until ``n`` more frames have been drawn: everything the server did before now is on screen."""
    f0 = page.evaluate("window.slamLab.drawn")
    page.wait_for_function(f"window.slamLab.drawn >= {f0 + n}", timeout=WAIT_MS)


def replied(page: Any, act: Any) -> None:
    """Do ``act`` (one command), wait for the server's reply to it and for frames drawn after that."""
    s0 = page.evaluate("window.slamLab.states")
    act()
    page.wait_for_function(f"window.slamLab.states > {s0}", timeout=WAIT_MS)
    next_frames(page)


def hold_until(page: Any, key: str, condition_js: str, timeout_ms: int = WAIT_MS) -> None:
    """Hold ``key`` until the library-reported state satisfies ``condition_js`` (STACK.md B3: never a fixed sleep)."""
    page.keyboard.down(key)
    try:
        page.wait_for_function(condition_js, timeout=timeout_ms)
    finally:
        page.keyboard.up(key)


def set_control(page: Any, name: str, value: Any) -> None:
    """Change a control the way a user does: set its value and fire its change event."""
    page.eval_on_selector(f"#ctl-{name}", "(e, v) => { if (e.type === 'checkbox') e.checked = v; else e.value = v; "
                                          "e.dispatchEvent(new Event('change')); }", value)


@pytest.mark.parametrize("slug", ["index"] + [p.slug for p in PAGES])
def test_page_loads_without_console_errors(page: Any, lab_server: str, artifacts: Path, slug: str) -> None:
    url = f"{lab_server}/" if slug == "index" else f"{lab_server}/lab/{slug}?hz=20"
    errors = open_page(page, url)
    if slug == "index":
        page.wait_for_function("window.slamLab && window.slamLab.status", timeout=WAIT_MS)
        assert page.locator("ul.pages a").count() == len(PAGES)
        status = page.evaluate("window.slamLab.status")
        assert status["estimators"] == estimator_names()
    else:
        page.wait_for_function(FRAMES, timeout=WAIT_MS)
        hello = page.evaluate("window.slamLab.hello")
        assert hello["page"] == slug
        # every control the server announced is on the page
        for p in hello["params"]:
            assert page.locator(f"#ctl-{p['name']}").count() == 1
        assert page.evaluate("window.slamLab.notices") == []  # every page's back end exists
        # the chapter's check question: a wrong answer, then the right one, each with its feedback
        check = CHECKS[slug]
        wrong = (check.answer + 1) % len(check.choices)
        page.locator(f"#check-choice-{wrong}").click()
        wait_or_explain(page, "window.slamLab.feedback && window.slamLab.feedback.correct === false")
        assert page.locator("#check-feedback.wrong").inner_text() == check.feedback[wrong]
        page.locator(f"#check-choice-{check.answer}").click()
        wait_or_explain(page, "window.slamLab.feedback && window.slamLab.feedback.correct === true")
        assert page.locator("#check-feedback.right").inner_text() == check.feedback[check.answer]
        # the chapter's try-this task, waiting to be done
        if slug in TASKS:
            assert page.locator("#task-prompt").inner_text() == TASKS[slug]
            assert page.evaluate("window.slamLab.task.result") is None
        else:
            assert page.locator("#task").count() == 0
    page.screenshot(path=str(artifacts / f"page-{slug}.png"), full_page=True)
    assert errors == []


def test_simulator_arrow_keys_move_the_robot(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=30&seed=3")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    before = page.evaluate("window.slamLab.pose")
    page.locator("#world").click()
    hold_until(page, "ArrowUp", f"Math.hypot(window.slamLab.pose[0] - {before[0]}, "
                                f"window.slamLab.pose[1] - {before[1]}) > 1.0")
    hold_until(page, "ArrowLeft", f"Math.abs(window.slamLab.pose[2] - {before[2]}) > 0.4")
    after = page.evaluate("window.slamLab.pose")
    assert abs(after[0] - before[0]) + abs(after[1] - before[1]) > 1.0
    # released keys: the robot stops. A parameter change answered by the server comes after the key-up was applied
    # (commands are applied in order); from the frames after that, the pose stays put
    set_control(page, "steps_per_s", 11)
    page.wait_for_function("window.slamLab.values.steps_per_s === 11", timeout=WAIT_MS)
    next_frames(page)
    p1 = page.evaluate("window.slamLab.pose")
    next_frames(page, 5)
    p2 = page.evaluate("window.slamLab.pose")
    assert p1 == pytest.approx(p2, abs=1e-6)
    page.screenshot(path=str(artifacts / "simulator-driven.png"))
    assert errors == []


def test_simulator_auto_explore_finds_landmarks_and_pause_stops(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=30&seed=5")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    set_control(page, "steps_per_s", 40)
    seen0 = page.evaluate("window.slamLab.counters.landmarks_seen")
    page.locator("#ctl-drive").select_option("explore")
    page.wait_for_function(f"window.slamLab.counters.landmarks_seen > {seen0 + 5}", timeout=WAIT_MS)
    page.locator("#ctl-paused").check()
    page.wait_for_function("window.slamLab.values.paused === true", timeout=WAIT_MS)
    next_frames(page)
    step = page.evaluate("window.slamLab.counters.step")
    next_frames(page, 5)
    assert page.evaluate("window.slamLab.counters.step") == step
    page.locator("#act-step").click()
    page.wait_for_function(f"window.slamLab.counters.step === {step + 1}", timeout=WAIT_MS)
    page.locator("#act-reset").click()
    page.wait_for_function("window.slamLab.counters.step === 0", timeout=WAIT_MS)
    assert errors == []


def test_simulator_sensor_range_changes_what_is_seen(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=30&seed=2")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    page.locator("#ctl-paused").check()
    set_control(page, "sensor_range_m", 1.0)
    page.wait_for_function("window.slamLab.values.sensor_range_m === 1", timeout=WAIT_MS)
    page.locator("#act-step").click()
    page.wait_for_function("window.slamLab.counters.step >= 1", timeout=WAIT_MS)
    next_frames(page)
    near = page.evaluate("window.slamLab.sections.OBSV ? window.slamLab.sections.OBSV[0] : 0")
    set_control(page, "sensor_range_m", 40.0)
    page.wait_for_function("window.slamLab.values.sensor_range_m === 40", timeout=WAIT_MS)
    page.locator("#act-step").click()
    page.wait_for_function("window.slamLab.counters.step >= 2", timeout=WAIT_MS)
    next_frames(page)
    far = page.evaluate("window.slamLab.sections.OBSV ? window.slamLab.sections.OBSV[0] : 0")
    assert far > near
    # a bad value typed by hand is refused by the server with a message, and the page carries on
    page.evaluate("window.slamLab.send({type: 'param', name: 'sensor_range_m', value: -3})")
    page.wait_for_function("window.slamLab.errors.length > 0", timeout=WAIT_MS)
    assert "sensor_range_m" in page.evaluate("window.slamLab.errors[0]")
    assert errors == []


def test_drift_motion_noise_slider_changes_ate(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/drift?hz=30&seed=1")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    set_control(page, "steps_per_s", 60)
    set_control(page, "motion_noise", 0)
    page.wait_for_function("window.slamLab.values.motion_noise === 0 && window.slamLab.counters.step > 40",
                           timeout=WAIT_MS)
    assert page.evaluate("window.slamLab.counters.ate_rmse_m") < 1e-6  # perfect odometry: no drift at all
    set_control(page, "motion_noise", 20)
    page.wait_for_function("window.slamLab.values.motion_noise === 20 && window.slamLab.counters.step > 40 && "
                           "window.slamLab.counters.ate_rmse_m > 0.05", timeout=WAIT_MS)
    assert errors == []


def test_ekf_state_dimension_counts_landmarks(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/ekf?hz=30&seed=4")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    set_control(page, "steps_per_s", 30)
    page.wait_for_function("window.slamLab.counters.landmarks_mapped >= 5", timeout=WAIT_MS)
    # counters and sections of one and the same frame
    c, sections = page.evaluate("[window.slamLab.counters, window.slamLab.sections]")
    # the state holds confirmed and tentative landmarks, 2 numbers each, after the 3 pose numbers
    tentative = c["landmarks_tentative"]
    assert tentative == tentative, "ekf reports its tentative landmarks (Estimate.tentative_landmarks)"
    assert c["state_dim"] == 3 + 2 * (c["landmarks_mapped"] + tentative)
    assert sections["ECOV"][0] == sections["ELMK"][0] == c["landmarks_mapped"]
    n = min(int(c["state_dim"]), 96)  # the heat map is block-averaged beyond 96 x 96
    assert sections["HEAT"] == [n, n]
    page.screenshot(path=str(artifacts / "ekf-running.png"), full_page=True)
    assert errors == []


def test_association_page_reports_precision(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/association?hz=10")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    c = page.evaluate("window.slamLab.counters")
    assert c["observations"] > 0
    methods = page.evaluate("window.slamLab.hello.params.find(p => p.name === 'method').choices")
    assert "known" in methods
    page.locator("#ctl-method").select_option("known")
    page.wait_for_function("window.slamLab.values.method === 'known'", timeout=WAIT_MS)
    next_frames(page)
    c = page.evaluate("window.slamLab.counters")
    assert c["precision"] == 1.0 and c["wrong"] == 0  # the oracle never mismatches
    before = page.evaluate("window.slamLab.counters.observations")
    for _ in range(5):  # scrambling draws a new scene; the number of observations changes at least once
        replied(page, lambda: page.locator("#act-scramble").click())
        if page.evaluate("window.slamLab.counters.observations") != before:
            break
    assert page.evaluate("window.slamLab.counters.observations") != before
    assert errors == []


def test_features_threshold_slider_changes_the_corner_count(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/features?hz=10")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    set_control(page, "threshold_rel", 0.01)
    page.wait_for_function("window.slamLab.values.threshold_rel === 0.01", timeout=WAIT_MS)
    next_frames(page)
    low = page.evaluate("window.slamLab.counters.corners_found")
    set_control(page, "threshold_rel", 0.9)
    page.wait_for_function("window.slamLab.values.threshold_rel === 0.9", timeout=WAIT_MS)
    page.wait_for_function(f"window.slamLab.counters.corners_found < {low}", timeout=WAIT_MS)
    page.screenshot(path=str(artifacts / "features-high-threshold.png"))
    assert errors == []


def test_fastslam_particle_slider_sets_the_particle_count(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/fastslam?hz=20&seed=2")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    page.locator("#ctl-estimator").select_option("fastslam")
    set_control(page, "particles", 17)
    page.wait_for_function("window.slamLab.values.particles === 17 && window.slamLab.counters.particles === 17 && "
                           "window.slamLab.sections.PART && window.slamLab.sections.PART[0] === 17", timeout=WAIT_MS)
    page.wait_for_function("window.slamLab.counters.step > 3", timeout=WAIT_MS)
    n_eff = page.evaluate("window.slamLab.counters.n_eff")
    assert 1.0 <= n_eff <= 17.0 + 1e-6  # N_eff = 1 / sum w^2 lies in [1, M]
    assert errors == []


def test_graph_optimize_button_runs_gauss_newton(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/graph?hz=20&seed=1")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    set_control(page, "steps", 60)
    page.wait_for_function("window.slamLab.counters.poses === 61", timeout=WAIT_MS)
    page.locator("#act-optimize").click()
    page.wait_for_function("window.slamLab.counters.iteration >= 2", timeout=WAIT_MS)
    c = page.evaluate("window.slamLab.counters")
    assert c["ate_now_m"] < c["ate_initial_m"]
    page.screenshot(path=str(artifacts / "graph-optimized.png"))
    assert errors == []


def test_simulator_arrow_into_a_wall_stops_the_robot(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=30&seed=3")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    set_control(page, "steps_per_s", 60)
    page.wait_for_function("window.slamLab.values.steps_per_s === 60", timeout=WAIT_MS)
    page.locator("#world").click()
    page.keyboard.down("ArrowUp")  # the robot starts at (3, 3) facing east; the east wall is at x = 20
    try:
        page.wait_for_function("window.slamLab.pose[0] > 19.5", timeout=WAIT_MS)
        page.wait_for_function(STILL, timeout=WAIT_MS)  # still holding the key: the robot stops at the wall
        p1 = page.evaluate("window.slamLab.pose")
        next_frames(page, 5)
        p2 = page.evaluate("window.slamLab.pose")
        held = page.evaluate("window.slamLab.values.steps_per_s") == 60
    finally:
        page.keyboard.up("ArrowUp")
    assert held and p1 == p2 and p1[0] <= 20.0 - 0.3 + 1e-3
    assert errors == []


# true once the drawn robot pose has not changed over 10 drawn frames
STILL = """() => {
  const l = window.slamLab, k = JSON.stringify(l.pose);
  if (window.__still === undefined || window.__still.k !== k) { window.__still = {k, f: l.drawn}; return false; }
  return l.drawn - window.__still.f >= 10;
}"""


# purple particle squares (COLORS.particle over white) in a canvas: the bounding box of their pixels
PURPLE_BOX = """(id) => {
  const c = document.getElementById(id), d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  let x0 = 1e9, x1 = -1, y0 = 1e9, y1 = -1;
  for (let i = 0; i < d.length; i += 4) {
    const r = d[i], g = d[i + 1], b = d[i + 2];
    if (b - g > 40 && r - g > 20) {
      const p = i / 4, x = p % c.width, y = Math.floor(p / c.width);
      x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
    }
  }
  return x1 < 0 ? 0 : Math.max(x1 - x0, y1 - y0);
}"""


def test_fastslam_particle_spread_is_visible(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/fastslam?hz=20&seed=0")
    page.wait_for_function(FRAMES + " && window.slamLab.counters.step > 20", timeout=WAIT_MS)
    spread = page.evaluate(PURPLE_BOX, "zoom")
    zoom = page.evaluate("window.slamLab.zoom")
    page.screenshot(path=str(artifacts / "fastslam-zoom.png"), full_page=True)
    assert spread >= 10, f"particle cloud drawn {spread} px wide"
    assert zoom["spreadPx"] >= 10 and zoom["barLabel"]
    assert errors == []


#: a copy of the world canvas's pixels, kept in the page (getImageData returns a copy; later drawing leaves it alone)
SAVE_WORLD = "() => { window.__worldBefore = document.getElementById('world').getContext('2d')" \
             ".getImageData(0, 0, 760, 540).data; }"
#: how many pixels' RGB differ from that copy now, counted in the page: shipping both snapshots' 1.6 M channel values
#: to Python as JSON arrays took ~16 s each
CHANGED_PIXELS = """() => {
  const a = window.__worldBefore;
  const b = document.getElementById('world').getContext('2d').getImageData(0, 0, 760, 540).data;
  let n = 0;
  for (let i = 0; i < a.length; i += 4) if (a[i] !== b[i] || a[i + 1] !== b[i + 1] || a[i + 2] !== b[i + 2]) n++;
  return n;
}"""


def test_loop_close_loop_now_changes_the_drawn_path_and_the_ate(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/loop?hz=20&seed=0")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    set_control(page, "steps_per_s", 60)
    page.wait_for_function("window.slamLab.counters.step >= 470", timeout=WAIT_MS)
    page.locator("#ctl-paused").check()
    page.wait_for_function("window.slamLab.values.paused === true", timeout=WAIT_MS)
    next_frames(page)
    ate_text = page.locator('[data-num="ate_rmse_m"]').inner_text()
    page.evaluate(SAVE_WORLD)
    page.screenshot(path=str(artifacts / "loop-before.png"))
    for _ in range(30):  # press where the robot sees its start again (a step further each time until accepted)
        page.evaluate("window.slamLab.notices = []")
        page.locator("#act-close_loop").click()
        page.wait_for_function("window.slamLab.notices.some(n => n.startsWith('close loop'))", timeout=WAIT_MS)
        if any("accepted" in n for n in page.evaluate("window.slamLab.notices")):
            break
        page.locator("#act-step").click()
    page.wait_for_function(f"document.querySelector('[data-num=\"ate_rmse_m\"]').textContent !== '{ate_text}'",
                           timeout=WAIT_MS)
    page.wait_for_function("window.slamLab.sections.GHST !== undefined", timeout=WAIT_MS)
    next_frames(page)
    changed = page.evaluate(CHANGED_PIXELS)
    page.screenshot(path=str(artifacts / "loop-after.png"))
    assert changed > 500, f"only {changed} pixels changed"
    assert float(page.locator('[data-num="ate_rmse_m"]').inner_text()) < float(ate_text)
    assert any("accepted" in n for n in page.evaluate("window.slamLab.notices"))
    assert errors == []


def test_panels_show_labels_with_units_and_only_rows_that_apply(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/ekf?hz=20")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    text = page.locator("#numbers").inner_text()
    assert "trajectory error, ATE RMSE (m)" in text and "ate_rmse_m" not in text and "ate rmse m" not in text
    assert "effective particles" not in text  # the EKF has no particles: no particle rows
    page.locator("#ctl-estimator").select_option("fastslam")
    page.wait_for_function("window.slamLab.rows.includes('n_eff')", timeout=WAIT_MS)
    assert "effective particles" in page.locator("#numbers").inner_text()
    assert errors == []


def test_graph_page_draws_the_true_path(page: Any, lab_server: str) -> None:
    errors = open_page(page, f"{lab_server}/lab/graph?hz=20&seed=1")
    page.wait_for_function(FRAMES + " && window.slamLab.counters.poses > 30", timeout=WAIT_MS)
    assert page.evaluate("window.slamLab.sections.TPTH")[0] > 30
    assert errors == []


def test_simulator_lidar_back_end_draws_its_occupancy_grid(page: Any, lab_server: str, artifacts: Path) -> None:
    errors = open_page(page, f"{lab_server}/lab/simulator?hz=20&seed=0")
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    page.locator("#ctl-drive").select_option("route")
    page.locator("#ctl-estimator").select_option("lidar")
    page.wait_for_function("window.slamLab.values.estimator === 'lidar'", timeout=WAIT_MS)
    set_control(page, "steps_per_s", 30)
    page.wait_for_function("window.slamLab.sections.GRID && window.slamLab.sections.GRID[0] > 10", timeout=WAIT_MS)
    assert any("lidar: a scan every" in n for n in page.evaluate("window.slamLab.notices"))
    page.screenshot(path=str(artifacts / "simulator-lidar-grid.png"))
    assert errors == []


def test_status_line_says_what_the_page_waits_for_and_when_the_server_is_gone(page: Any, lab_server: str) -> None:
    """While the server builds the session (held back here: the server's messages wait in the test), the status
    says so and counts the seconds; once frames flow it gives the rates; after the connection drops it says
    disconnected and keeps saying it (the once-a-second rates used to overwrite it with "0.0 frames/s")."""
    held: list[Any] = []
    route: dict[str, Any] = {}

    def from_server(msg: Any) -> None:
        if route.get("hold", True):
            held.append(msg)
        else:
            route["page"].send(msg)

    def on_socket(ws: Any) -> None:
        route["page"] = ws
        ws.connect_to_server().on_message(from_server)

    page.route_web_socket("**/ws/problem*", on_socket)
    errors = open_page(page, f"{lab_server}/lab/problem?hz=20")
    page.wait_for_function("window.slamLab && window.slamLab.connected && window.slamLab.statusTicks >= 2",
                           timeout=WAIT_MS)
    assert page.evaluate("window.slamLab.hello") is None
    assert "building this page's session" in page.inner_text("#status")
    while held:  # in order: messages that arrive while these are sent join the queue
        route["page"].send(held.pop(0))
    route["hold"] = False
    page.wait_for_function(FRAMES, timeout=WAIT_MS)
    ticks = page.evaluate("window.slamLab.statusTicks")
    page.wait_for_function(f"window.slamLab.statusTicks >= {ticks + 1}", timeout=WAIT_MS)
    assert "frames/s received" in page.inner_text("#status")
    route["page"].close()
    page.wait_for_function("!window.slamLab.connected", timeout=WAIT_MS)
    ticks = page.evaluate("window.slamLab.statusTicks")
    page.wait_for_function(f"window.slamLab.statusTicks >= {ticks + 2}", timeout=WAIT_MS)
    assert page.inner_text("#status") == "disconnected from the lab server"
    assert errors == []
