"""``slam2d lab``: prints its URL, serves, binds loopback by default, rejects a bad port."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
import urllib.request

import pytest

from slam2d.cli.main import main


def test_lab_prints_its_url_and_serves() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    with subprocess.Popen([sys.executable, "-m", "slam2d", "lab", "--port", str(port)], stdout=subprocess.PIPE,
                          stderr=subprocess.DEVNULL, text=True) as proc:
        _check_lab(proc, port)


def _check_lab(proc: subprocess.Popen[str], port: int) -> None:
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert f"http://127.0.0.1:{port}/" in line
        deadline = time.monotonic() + 20
        while True:
            try:
                html = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=1).read().decode()
                break
            except OSError:
                assert time.monotonic() < deadline and proc.poll() is None
                time.sleep(0.1)
        assert "slam2d lab" in html
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/lab/simulator", timeout=5).read().decode()
        assert 'src="/static/js/lab.js"' in page and "cdn" not in page.lower()
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_lab_rejects_a_bad_port(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["lab", "--port", "70000"]) == 2
    assert "--port" in capsys.readouterr().err
