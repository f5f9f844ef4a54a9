"""The warehouse design-challenge page in headless chromium: relocalisation hypotheses then a decision, the static
layer drawn, the controls (start mode, floor markers, forklift count) applied by the server."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from slam2d.geometry import se2
from slam2d.maps.layers import DYNAMIC, STATIC, LayersConfig, MapLayers
from slam2d.sim.world import segment_distances
from slam2d.web.frames import decode_frame, encode_frame
from slam2d.web.params import CommandError
from slam2d.web.sessions.warehouse import ON_FORKLIFT_M, WarehouseSession, max_forklifts, saved_map, scenario

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


@pytest.mark.browser
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
    page.wait_for_function("window.slamLab.gridSample && window.slamLab.gridSample.occ.length > 50", timeout=30_000)
    px = page.evaluate(PIXELS)
    dark = sum(v < 100 for v in px["occ"]) / len(px["occ"])
    light = sum(v > 200 for v in px["free"]) / len(px["free"])
    assert dark > 0.8 and light > 0.8, (dark, light)
    page.screenshot(path=str(artifacts / "warehouse.png"), full_page=True)
    assert errors == []


@pytest.mark.browser
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
    page.wait_for_function("window.slamLab.errors.some(e => e.includes('forklifts'))", timeout=30_000)
    assert page.evaluate("window.slamLab.values.forklifts") == 3
    # back to the saved map
    page.locator("#ctl-start").select_option("saved map")
    page.wait_for_function("window.slamLab.relocText.startsWith('undecided') || "
                           "window.slamLab.relocText.startsWith('relocalised')", timeout=30_000)
    assert errors == []


def test_forklift_range_is_the_scenario_validation() -> None:
    hi = max_forklifts()
    scenario(0, hi, False)  # the largest count the layout holds is valid ...
    with pytest.raises(ValueError, match="moving_objects"):
        scenario(0, hi + 1, False)  # ... and one more is refused by the scenario itself


def test_session_numbers_come_from_the_relocaliser_and_the_simulator() -> None:
    s = WarehouseSession(seed=0)
    with pytest.raises(CommandError, match="forklifts"):
        s.apply({"type": "param", "name": "forklifts", "value": max_forklifts() + 1})
    seen = []
    for _ in range(60):
        s.step_once()
        _, sec = decode_frame(encode_frame(0, s.sections()))
        nums = dict(zip(s.scalars, sec["NUMS"][0].tolist(), strict=True))
        rel = s.est.relocaliser
        assert rel is not None
        if not s.est.relocalised:
            assert nums["hypotheses"] == len(rel.hyp) and len(sec["HYPO"]) == len(rel.hyp)
            seen.append(len(rel.hyp))
        else:
            assert "HYPO" not in sec and nums["accepted_step"] == s.est.accepted_step - s.start_step
        assert len(sec["FORK"]) == 4 * len(s.sim.world.moving)
        e = se2.local(s.sim.pose, s.est.estimate().pose)
        assert nums["error_m"] == pytest.approx(np.hypot(e[0], e[1]), abs=1e-4)
    assert max(seen) > 1  # several hypotheses at first
    h = sec["HHIS"]
    assert len(h) == len(rel.history) and np.all(np.diff(h[:, 0]) >= 0)


def test_cold_start_has_no_relocaliser_and_draws_its_own_static_layer() -> None:
    s = WarehouseSession(seed=2)
    s.apply({"type": "param", "name": "start", "value": "cold start"})
    assert s.est.relocaliser is None and s.prior is None
    assert "hypotheses" not in s.rows() and "keyframes" in s.rows()
    for _ in range(40):
        s.step_once()
    sec = dict(s.sections())
    assert "HYPO" not in sec and "GRID" in sec
    grid = s.est.lidar.map_layers().static_grid()
    nums = dict(zip(s.scalars, sec["NUMS"].tolist(), strict=True))
    assert nums["static_cells"] == float((grid.probability() > 0.65).sum())
    assert nums["keyframes"] == s.est.lidar.layer_stats().keyframes >= 1


def test_scan_points_are_drawn_by_the_estimators_labels_and_forklifts_are_checked_against_truth() -> None:
    s = WarehouseSession(seed=0)
    shares = []
    for _ in range(300):
        s.step_once()
        if not s.est.relocalised:
            continue
        sec = dict(s.sections())
        nums = dict(zip(s.scalars, sec["NUMS"].tolist(), strict=True))
        pts, labels = s.est.lidar.last_labels()
        world = se2.transform_points(s.est.estimate().pose, pts)
        for name, want in (("SCAN", labels == STATIC), ("SDYN", labels == DYNAMIC),
                           ("SPND", (labels != STATIC) & (labels != DYNAMIC))):
            got = sec.get(name, np.zeros((0, 2)))
            np.testing.assert_allclose(got, world[want], atol=1e-4)  # frames carry float32
        assert nums["dynamic_points"] == np.count_nonzero(labels == DYNAMIC)
        lay = s.est.lidar.map_layers()
        assert nums["dynamic_cells"] == len(lay.dynamic_points(s.sim.time_s)) == len(sec.get("DYNL", ()))
        assert nums["promoted"] == lay.promoted and nums["marker_fixes"] == s.est.lidar.layer_stats().marker_fixes
        # the forklift share, recomputed here from the truth outlines at the scan's time and the true pose
        fork = np.vstack([m.segments(s.sim.time_s) for m in s.sim.world.moving])
        on = segment_distances(se2.transform_points(s.sim.pose, pts), fork).min(axis=1) < ON_FORKLIFT_M
        assert nums["forklift_points"] == on.sum()
        if on.any():
            shares.append(nums["forklift_dynamic_pct"])
            assert nums["forklift_dynamic_pct"] == pytest.approx(100 * np.mean(labels[on] == DYNAMIC), abs=1e-3)
    assert s.est.relocalised and len(shares) > 10
    assert np.mean(shares) > 80  # forklifts in view are mostly labelled dynamic (the rest: pending, new ground)
    assert nums["error_m"] < 0.1 and nums["marker_fixes"] > 0  # surveyed markers keep the pose within centimetres


def test_the_saved_map_carries_a_static_layer_the_session_localises_against() -> None:
    prior = saved_map(0)
    lay = MapLayers.from_saved(LayersConfig(), prior.layers)
    walls = WarehouseSession(seed=0).sim.world.walls
    d = segment_distances(lay.static_points(), walls).min(axis=1)
    assert len(d) > 1000 and np.quantile(d, 0.95) < 0.15  # the static layer is the racks and walls, not forklifts
