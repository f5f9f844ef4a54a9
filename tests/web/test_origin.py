"""The lab refuses other sites: foreign Origin (websocket and HTTP) and foreign Host are refused; slow clients time
out; ``slam2d lab`` announces its URL only after the bind succeeded. Every process is ended by its PID."""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from collections.abc import Iterator

import pytest
import websockets

from slam2d.web.app import origin_allowed

PY = sys.executable


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def lab() -> Iterator[tuple[int, subprocess.Popen[str]]]:
    port = _free_port()
    proc = subprocess.Popen([PY, "-m", "slam2d", "lab", "--port", str(port), "--allow-origin", "https://ok.example"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert f"http://127.0.0.1:{port}/" in proc.stdout.readline()  # printed only after the bind
        yield port, proc
    finally:
        proc.terminate()
        try:
            _, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
    assert "Traceback" not in err, err[-3000:]


def _hello(port: int, origin: str | None) -> str:
    async def go() -> str:
        async with websockets.connect(f"ws://127.0.0.1:{port}/ws/simulator?hz=5", compression=None,
                                      origin=origin, open_timeout=60) as ws:  # type: ignore[arg-type]
            return str(json.loads(await asyncio.wait_for(ws.recv(), 60))["type"])

    # in a thread of its own: a browser test earlier in the session leaves an event loop running in this thread
    with concurrent.futures.ThreadPoolExecutor(1) as ex:
        return ex.submit(lambda: asyncio.run(go())).result()


def test_a_websocket_from_a_foreign_origin_is_refused(lab) -> None:
    port, _ = lab
    with pytest.raises(websockets.InvalidStatus) as e:
        _hello(port, "http://evil.example")
    assert e.value.response.status_code == 403
    assert _hello(port, f"http://127.0.0.1:{port}") == "hello"
    assert _hello(port, "https://ok.example") == "hello"  # --allow-origin
    assert _hello(port, None) == "hello"  # scripts send no Origin


def _get(port: int, headers: dict[str, str]) -> int:
    req = urllib.request.Request(f"http://127.0.0.1:{port}/api/status", headers=headers)
    try:
        return int(urllib.request.urlopen(req, timeout=60).status)
    except urllib.error.HTTPError as e:
        return int(e.code)


def test_http_with_a_foreign_origin_or_host_is_refused(lab) -> None:
    port, _ = lab
    assert _get(port, {}) == 200
    assert _get(port, {"Origin": f"http://localhost:{port}"}) == 200
    assert _get(port, {"Origin": "https://evil.example"}) == 403
    assert _get(port, {"Host": "evil.example"}) == 403  # DNS rebinding


@pytest.mark.parametrize(("origin", "ok"), [
    ("http://localhost:8000", True), ("http://127.0.0.1", True), ("http://[::1]:8000", True),
    ("https://localhost", True), ("http://localhost.evil.example", False), ("http://127.0.0.1.evil.example", False),
    ("null", False), ("file://", False), ("http://evil.example", False), ("ws://127.0.0.1", False)])
def test_origin_rule(origin: str, ok: bool) -> None:
    assert origin_allowed(origin, frozenset()) is ok


def test_slow_client_is_timed_out_and_busy_port_is_one_error_line(lab) -> None:
    port, _ = lab
    second = subprocess.run([PY, "-m", "slam2d", "lab", "--port", str(port)], capture_output=True, text=True,
                            timeout=120)
    assert second.returncode != 0 and "serving on" not in second.stdout
    err = second.stderr.strip().splitlines()
    assert len(err) == 1 and str(port) in err[0] and "Traceback" not in second.stderr, err
    # a client that never finishes its headers is disconnected by the server
    with socket.create_connection(("127.0.0.1", port), timeout=60) as s:
        s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        assert s.recv(100) == b""  # closed by the server (a socket timeout would raise instead)
