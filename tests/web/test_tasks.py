"""Each chapter's "Try this" task: doing it (through the same commands the page sends) makes the session report it
done, quoting numbers from the run; not doing it leaves the page waiting."""

from __future__ import annotations

import re
from typing import Any

import pytest

from slam2d.web.pages import PAGE_BY_SLUG, PAGES
from slam2d.web.tasks import TASKS


def _param(s: Any, name: str, value: Any) -> None:
    s.apply({"type": "param", "name": name, "value": value})


def _steps(s: Any, n: int) -> None:
    for _ in range(n):
        s.apply({"type": "action", "name": "step"})
        if s.task_result is not None:
            return


def _numbers(text: str) -> list[float]:
    return [float(x) for x in re.findall(r"-?\d+\.\d+", text)]


def test_every_chapter_has_a_task_in_its_hello() -> None:
    slugs = {p.slug for p in PAGES}
    assert set(TASKS) <= slugs and {p.slug for p in PAGES if p.number <= 10} <= set(TASKS)  # chapters 0-10
    for p in PAGES:
        hello = p.make(0).hello()
        assert hello["task"] == ({"prompt": TASKS[p.slug], "result": None} if p.slug in TASKS else None)


def test_maps_and_connections_tasks() -> None:
    s = PAGE_BY_SLUG["maps"].make(0)
    for _ in range(5):
        s.advance(0.5)
    for layer in ("points", "occupancy"):
        _param(s, "layer", layer)
    assert s.task_result is None  # topology not shown yet
    _param(s, "layer", "topology")
    assert s.task_result is not None and "grid" in s.task_result
    c = PAGE_BY_SLUG["connections"].make(0)
    for _ in range(5):
        c.advance(0.5)
    _param(c, "layer", "occupancy")
    occ, free = (int(x) for x in re.findall(r"(\d+) cells occupied and (\d+) free", c.task_result or "")[0])
    assert occ == int(c.grid.occupied().sum()) and free == int(c.grid.free().sum()) and occ > 0 and free > 0


def test_features_task_quotes_precision_and_recall() -> None:
    s = PAGE_BY_SLUG["features"].make(0)
    _param(s, "threshold_rel", 0.4)
    assert s.task_result is None  # high without having been low first
    _param(s, "threshold_rel", 0.02)
    low = (len(s.detected), s.score.precision)
    _param(s, "threshold_rel", 0.35)
    assert s.task_result is not None
    assert f"corners found {low[0]} -> {len(s.detected)}" in s.task_result
    assert f"precision {low[1]:.2f} -> {s.score.precision:.2f}" in s.task_result


def test_association_task_compares_greedy_and_jcbb() -> None:
    s = PAGE_BY_SLUG["association"].make(3)
    _param(s, "pose_sigma_m", 1.2)
    _param(s, "method", "nn")
    greedy_wrong = int(s.numbers()["wrong"])
    assert s.task_result is None
    _param(s, "method", "jcbb")
    assert s.task_result is not None
    assert f"nn made {greedy_wrong} wrong" in s.task_result
    assert f"jcbb made {int(s.numbers()['wrong'])} wrong" in s.task_result


def test_graph_task_reports_the_cost_drop() -> None:
    s = PAGE_BY_SLUG["graph"].make(1)
    _param(s, "steps", 60)
    for _ in range(20):
        s.advance(0.5)
    s.apply({"type": "action", "name": "optimize"})
    for _ in range(60):
        s.advance(0.5)
        if s.converged:
            break
    assert s.task_result is not None and f"to {s.cost:.4g} in {s.iteration}" in s.task_result


def test_problem_task_compares_ekf_and_dead_reckoning() -> None:
    s = PAGE_BY_SLUG["problem"].make(0)
    _param(s, "paused", True)
    _steps(s, 200)
    assert s.task_result is None
    _param(s, "estimator", "dead-reckoning")
    _steps(s, 200)
    assert s.task_result is not None and "ekf" in s.task_result and "dead-reckoning" in s.task_result
    ekf_ate, dr_ate = _numbers(s.task_result)[:2]
    assert dr_ate == pytest.approx(s.ate_rmse(), abs=1e-3) and dr_ate > ekf_ate


def test_drift_task_compares_no_noise_with_noise() -> None:
    s = PAGE_BY_SLUG["drift"].make(0)
    _param(s, "paused", True)
    _param(s, "motion_noise", 0.0)
    _steps(s, 100)
    _param(s, "motion_noise", 10.0)
    _steps(s, 100)
    assert s.task_result is not None
    none, noisy = _numbers(s.task_result)[:2]
    assert none == 0.0 and noisy == pytest.approx(s.ate_rmse(), abs=1e-3) and noisy > 0.0


def test_fastslam_task_sees_the_resampling() -> None:
    s = PAGE_BY_SLUG["fastslam"].make(0)
    _param(s, "paused", True)
    _param(s, "particles", 10)
    _steps(s, 400)
    assert s.task_result is not None and "10 particles" in s.task_result and s.resamples >= 1


@pytest.mark.parametrize("slug", ["ekf", "simulator"])
def test_big_loop_task_notices_the_return_and_the_correction(slug: str) -> None:
    s = PAGE_BY_SLUG[slug].make(0)
    _param(s, "paused", True)
    if slug == "simulator":
        _param(s, "drive", "route")
    _steps(s, 1500)
    assert s.task_result is not None and "back at the start" in s.task_result
    back = int(re.findall(r"at step (\d+)", s.task_result)[0])
    assert s.sim.index == back + 20  # reported TASK_SETTLE_STEPS after the return
    assert f"-> {s.numbers()['pose_error_m']:.3f} m" in s.task_result


def test_big_loop_task_with_a_graph_back_end_points_at_the_moved_path() -> None:
    s = PAGE_BY_SLUG["simulator"].make(0)
    _param(s, "paused", True)
    _param(s, "estimator", "graph")
    _param(s, "drive", "route")
    _steps(s, 1500)
    assert s.task_result is not None and "re-estimates the past" in s.task_result


def test_loop_task_is_done_by_the_accepted_closure() -> None:
    s = PAGE_BY_SLUG["loop"].make(0)
    _param(s, "paused", True)
    _steps(s, 470)
    assert s.task_result is None
    before = s.ate_rmse()
    s.apply({"type": "action", "name": "close_loop"})
    assert s.task_result is not None
    moved, a0, a1 = _numbers(s.task_result)[:3]
    assert a0 == pytest.approx(before, abs=1e-3) and a1 == pytest.approx(s.ate_rmse(), abs=1e-3) and a1 < a0
    assert moved > 0.3
