"""QA pass on the lab server: what a page's controls really change, and the limits that keep one client (or one
combination of sliders) from exhausting the machine."""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import socket
import threading
from typing import Any

import numpy as np
import pytest
import websockets

from slam2d.graph.lidar import LidarSLAM
from slam2d.web.pages import PAGE_BY_SLUG
from slam2d.web.params import CommandError
from slam2d.web.sessions.sim import MAX_PARTICLE_LANDMARKS

RECV_TIMEOUT_S = 120


def _param(s: Any, name: str, value: Any) -> None:
    s.apply({"type": "param", "name": name, "value": value})


def test_lidar_lifelong_on_the_simulator_gets_scans_not_odometry_under_its_name() -> None:
    """The estimator list offers lidar-lifelong: the simulator must scan for it (as for lidar), so its estimate is
    its own, not dead reckoning's."""
    runs = {}
    for name in ("lidar-lifelong", "dead-reckoning"):
        s = PAGE_BY_SLUG["simulator"].make(0)
        _param(s, "drive", "explore")
        _param(s, "estimator", name)
        for _ in range(40):
            s.apply({"type": "action", "name": "step"})
        runs[name] = s
    ll = runs["lidar-lifelong"]
    assert isinstance(ll.est, LidarSLAM) and ll.values["estimator"] == "lidar-lifelong"
    assert ll.sim.config.lidar.enabled and ll.last_step is not None and ll.last_step.scan is not None
    assert "GRID" in dict(ll.sections())  # the occupancy grid the notice promises
    assert not np.allclose(ll.trajectory(), runs["dead-reckoning"].trajectory())


def test_lidar_lifelong_outside_the_lidar_worlds_falls_back_with_a_notice() -> None:
    s = PAGE_BY_SLUG["simulator"].make(0)
    _param(s, "scenario", "grid")
    _param(s, "estimator", "lidar-lifelong")
    assert s.values["estimator"] == "dead-reckoning"
    assert any("'lidar-lifelong' matches scans against walls" in n for n in s.notices)


def test_particles_times_landmarks_is_bounded_and_a_refused_setting_changes_nothing() -> None:
    """2000 particles x 2000 landmarks (each slider within its range) took 1.2 GB after 30 steps: refused with a
    message naming the limit; the session keeps running what it ran."""
    s = PAGE_BY_SLUG["simulator"].make(0)
    _param(s, "landmarks", 2000)
    _param(s, "particles", 2000)  # the EKF ignores particles: accepted
    sim_before = s.sim
    with pytest.raises(CommandError, match=f"{MAX_PARTICLE_LANDMARKS} landmark filters"):
        _param(s, "estimator", "fastslam")
    assert s.values["estimator"] == "ekf" and s.sim is sim_before
    _param(s, "landmarks", 50)
    _param(s, "estimator", "fastslam")  # 2000 x 50 fits
    with pytest.raises(CommandError, match="at most 100 particles"):
        _param(s, "landmarks", 2000)
    assert s.values["landmarks"] == 50 and len(s.sim.world.landmark_ids) == 50
    assert s.est.config.particles == 2000  # type: ignore[attr-defined]


def _run(coro: Any) -> Any:
    with concurrent.futures.ThreadPoolExecutor(1) as ex:
        return ex.submit(asyncio.run, asyncio.wait_for(coro, 5 * RECV_TIMEOUT_S)).result()


async def _first_text(ws: Any) -> dict[str, Any]:
    while True:
        msg = await asyncio.wait_for(ws.recv(), RECV_TIMEOUT_S)
        if isinstance(msg, str):
            return dict(json.loads(msg))


def test_sessions_beyond_the_limit_are_refused_with_a_message_and_a_closed_one_frees_its_place() -> None:
    import uvicorn

    from slam2d.web.app import create_app

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    srv = uvicorn.Server(uvicorn.Config(create_app(max_sessions=2), host="127.0.0.1", port=port, log_level="error"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    url = f"ws://127.0.0.1:{port}/ws/maps?hz=5"

    async def go() -> tuple[dict[str, Any], int | None, dict[str, Any]]:
        for _ in range(400):
            if srv.started:
                break
            await asyncio.sleep(0.05)
        async with websockets.connect(url, compression=None) as a, websockets.connect(url, compression=None) as b:
            assert (await _first_text(a))["type"] == "hello"
            assert (await _first_text(b))["type"] == "hello"
            async with websockets.connect(url, compression=None) as c:
                refused = await _first_text(c)
                with pytest.raises(websockets.ConnectionClosed):
                    await asyncio.wait_for(c.recv(), RECV_TIMEOUT_S)
                code = c.close_code
        for _ in range(200):  # the server sees both closes; then a new page gets its session
            async with websockets.connect(url, compression=None) as d:
                again = await _first_text(d)
            if again["type"] == "hello":
                break
            await asyncio.sleep(0.05)
        return refused, code, again

    try:
        refused, code, again = _run(go())
    finally:
        srv.should_exit = True
        thread.join(30)
    assert refused["type"] == "error" and "too many pages open" in refused["message"], refused
    assert code == 1013
    assert again["type"] == "hello"


def test_two_pages_opening_a_new_warehouse_seed_at_once_build_its_saved_map_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The saved map takes 13-20 s to build: the second tab waits for the first tab's build instead of repeating
    it. (The build is replaced by a slow counter; the cache is emptied before and after.)"""
    import time

    from slam2d.web.sessions import warehouse

    builds: list[int] = []

    def slow_simulate(config: Any, seed: int) -> Any:
        builds.append(seed)
        time.sleep(0.5)
        return seed

    monkeypatch.setattr(warehouse, "simulate", slow_simulate)
    monkeypatch.setattr(warehouse, "snapshot_from_truth", lambda log, layers: ("snapshot", log))
    warehouse._build_saved_map.cache_clear()
    try:
        with concurrent.futures.ThreadPoolExecutor(3) as ex:
            got = list(ex.map(warehouse.saved_map, [7, 7, 7]))
    finally:
        warehouse._build_saved_map.cache_clear()
    assert got == [("snapshot", 7)] * 3
    assert builds == [7]
