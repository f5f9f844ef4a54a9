"""The lab's fleet view: ``/api/fleet`` asks a running map server (here one in a thread of the test, fed
in-process) and refuses addresses off this machine; ``/fleet`` draws it in chromium."""

from __future__ import annotations

import json
import threading
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("zmq")

from slam2d.fleet.protocol import decode, encode, info_upper, pack_descriptor, pack_points
from slam2d.fleet.server import MapServer


@pytest.fixture
def running(tmp_path: Path) -> Iterator[str]:
    server = MapServer(tmp_path / "map.db")
    rng = np.random.default_rng(0)
    for d in (0, 1):
        ident = f"c{d}".encode()
        assert decode(server.handle(ident, encode({"type": "hello", "drone": d, "session": f"s{d}",
                                                   "dock": [2.0, 3.0 + d, 0.0]})))["type"] == "welcome"
        kfs = [{"id": k, "stamp": float(k), "pose": [2.0 + k, 3.0 + d, 0.0], "desc": pack_descriptor(np.ones(17) / 17),
                "pts": pack_points(rng.uniform(-3, 3, (40, 2)))} for k in range(4)]
        edges = [{"a": k - 1, "b": k, "z": [1.0, 0.0, 0.0], "info": info_upper(np.eye(3) * 100)} for k in range(1, 4)]
        assert decode(server.handle(ident, encode({"type": "delta", "drone": d, "seq": 1, "keyframes": kfs,
                                                   "edges": edges})))["type"] == "ack"
    stop = threading.Event()
    bound: list[str] = []
    t = threading.Thread(target=server.serve, kwargs={"ready": bound.append, "stop_event": stop}, daemon=True)
    t.start()
    for _ in range(200):
        if bound:
            break
        threading.Event().wait(0.05)
    assert bound
    yield bound[0]
    stop.set()
    t.join(10)
    server.close()


def get(url: str) -> tuple[int, Any]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def api(lab: str, server: str) -> tuple[int, dict[str, Any]]:
    code, text = get(f"{lab}/api/fleet?server={urllib.parse.quote(server)}")
    return code, json.loads(text)


def test_api_fleet_reports_a_running_server(running: str, lab_server: str) -> None:
    code, snap = api(lab_server, running)
    assert code == 200, snap
    assert [d["drone"] for d in snap["drones"]] == [0, 1]
    assert all(d["keyframes"] == 4 and len(d["xy"]) == 4 for d in snap["drones"])
    np.testing.assert_allclose(snap["drones"][1]["xy"][0], [2.0, 4.0], atol=0.02)
    code, page = get(f"{lab_server}/fleet")
    assert code == 200 and "/api/fleet" in page
    assert 'href="/fleet"' in get(f"{lab_server}/")[1]


def test_api_fleet_refuses_other_hosts_and_reports_a_missing_server(lab_server: str) -> None:
    for bad in ("tcp://10.0.0.1:5555", "tcp://example.org:5555", "ipc:///tmp/x", "tcp://127.0.0.1:0"):
        code, r = api(lab_server, bad)
        assert code == 400 and "127.0.0.1" in r["error"]
    import socket

    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code, r = api(lab_server, f"tcp://127.0.0.1:{port}")
    assert code == 503 and "map-server" in r["error"]


@pytest.mark.browser
def test_fleet_page_draws_the_drones(running: str, lab_server: str, page: Any, artifacts: Path) -> None:
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"{lab_server}/fleet?server={urllib.parse.quote(running)}")
    page.wait_for_function("document.querySelectorAll('#drones tbody tr').length === 2", timeout=60_000)
    assert "2 drones" in page.inner_text("#status")
    page.screenshot(path=str(artifacts / "fleet.png"))
    assert errors == []
