"""Fixtures for the web lab: a lab server in a subprocess, and Playwright driving Debian's chromium.

Browser tests skip cleanly when /usr/bin/chromium is absent (``make test`` installs it); the browser is never
downloaded (no ``playwright install``).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = Path("/usr/bin/chromium")
# the real binary, bypassing the Debian wrapper script (its /etc/chromium.d snippets print noise; STACK.md B1)
CHROMIUM_BIN = Path("/usr/lib/chromium/chromium")
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_lab(port: int) -> subprocess.Popen[bytes]:
    """``slam2d lab`` in a subprocess (isolated: a crash in the app cannot take the test process with it)."""
    proc = subprocess.Popen([sys.executable, "-m", "slam2d", "lab", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120  # a loaded machine imports slowly
    while True:
        try:
            urllib.request.urlopen(url + "/api/status", timeout=1).read()
            return proc
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                err = proc.communicate()[1].decode(errors="replace")
                raise RuntimeError(f"lab server did not start: {err[-2000:]}") from None
            time.sleep(0.1)


def stop_lab(proc: subprocess.Popen[bytes]) -> str:
    proc.terminate()
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return err.decode(errors="replace")


@pytest.fixture(scope="session")
def lab_process() -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """A lab server for the whole test session: ("127.0.0.1:PORT", process). Its stderr must hold no traceback."""
    port = free_port()
    proc = start_lab(port)
    yield f"127.0.0.1:{port}", proc
    err = stop_lab(proc)
    assert "Traceback" not in err, err[-3000:]


@pytest.fixture(scope="session")
def lab_server(lab_process: tuple[str, subprocess.Popen[bytes]]) -> str:
    return f"http://{lab_process[0]}"


@pytest.fixture(scope="session")
def browser_type_launch_args(browser_type_launch_args: dict[str, Any], tmp_path_factory: pytest.TempPathFactory
                             ) -> dict[str, Any]:
    if not CHROMIUM.exists():
        pytest.skip("Debian chromium (/usr/bin/chromium) is not installed; `make test` installs it")
    home = tmp_path_factory.mktemp("chromium-home")  # keeps ~/.config/chromium and ~/.cache/dconf out of HOME
    exe = CHROMIUM_BIN if CHROMIUM_BIN.exists() else CHROMIUM
    return {**browser_type_launch_args, "executable_path": str(exe), "env": {**os.environ, "HOME": str(home)}}


@pytest.fixture
def artifacts() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS
