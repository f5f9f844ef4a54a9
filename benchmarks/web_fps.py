"""Frame rate of the web lab with 500 landmarks and 500 covariance ellipses, measured inside headless chromium.

The page counts frames it received and frames it drew (``window.slamLab.frames`` / ``drawn``); this script reads
those counters over a fixed window. The lab server, the browser and this script share the machine's cores.

    .venv/bin/python benchmarks/web_fps.py [--seconds 5] [--hz 60]

Ellipses: with estimator ``ekf`` registered, the EKF's own landmark covariances (after it has mapped all 500
landmarks); otherwise the world-frame covariances of the 500 observations of one scan (``G_z R G_z^T``).
Needs Debian chromium at /usr/bin/chromium.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

LANDMARKS = 500


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--hz", type=int, default=60)
    ap.add_argument("--json", default=None, help="also write the result here")
    args = ap.parse_args()
    if not Path("/usr/bin/chromium").exists():
        print("skipped: /usr/bin/chromium is not installed")
        return 0
    from playwright.sync_api import sync_playwright

    from slam2d.lab.registry import estimator_names

    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "slam2d", "lab", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    try:
        for _ in range(200):
            try:
                urllib.request.urlopen(url + "/api/status", timeout=1).read()
                break
            except OSError:
                time.sleep(0.1)
        use_ekf = "ekf" in estimator_names()
        exe = "/usr/lib/chromium/chromium" if Path("/usr/lib/chromium/chromium").exists() else "/usr/bin/chromium"
        with tempfile.TemporaryDirectory() as home, sync_playwright() as p:
            browser = p.chromium.launch(executable_path=exe, env={**os.environ, "HOME": home})
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(f"{url}/lab/simulator?hz={args.hz}&seed=0")
            page.wait_for_function("window.slamLab && window.slamLab.hello && window.slamLab.drawn > 2")

            def send(name: str, value: object) -> None:
                page.evaluate("([n, v]) => window.slamLab.send({type: 'param', name: n, value: v})", [name, value])

            send("paused", True)
            send("scenario", "grid")
            send("landmarks", LANDMARKS)
            send("sensor_range_m", 100.0)
            if use_ekf:
                send("estimator", "ekf")
                send("paused", False)
                page.wait_for_function(f"window.slamLab.counters.landmarks_mapped >= {LANDMARKS}", timeout=120_000)
                send("paused", True)
                # the pause is applied after the EKF step in progress (seconds with 500 landmarks in view)
                page.wait_for_function("window.slamLab.values.paused === true", timeout=120_000)
                tag = "ECOV"
            else:
                send("obs_ellipses", True)
                page.evaluate("window.slamLab.send({type: 'action', name: 'step'})")
                tag = "OCOV"
            page.wait_for_function(f"window.slamLab.sections.{tag} && window.slamLab.sections.{tag}[0] >= "
                                   f"{LANDMARKS}", timeout=30_000)
            page.wait_for_timeout(1000)
            t0 = page.evaluate("[performance.now(), window.slamLab.frames, window.slamLab.drawn, "
                               "window.slamLab.bytes]")
            page.wait_for_timeout(int(args.seconds * 1000))
            t1 = page.evaluate("[performance.now(), window.slamLab.frames, window.slamLab.drawn, "
                               "window.slamLab.bytes]")
            draw_ms = page.evaluate("window.slamLab.drawMs")
            shape = page.evaluate(f"window.slamLab.sections.{tag}")
            page.screenshot(path=str(Path(tempfile.gettempdir()) / "web_fps.png"))
            browser.close()
        dt = (t1[0] - t0[0]) / 1000.0
        result = {
            "landmarks": LANDMARKS, "ellipses": shape[0], "ellipse_source": "ekf landmark_covs" if use_ekf else
            "observation covariances (no ekf registered)", "target_hz": args.hz, "seconds": round(dt, 2),
            "received_fps": round((t1[1] - t0[1]) / dt, 1), "drawn_fps": round((t1[2] - t0[2]) / dt, 1),
            "kib_per_frame": round((t1[3] - t0[3]) / max(t1[1] - t0[1], 1) / 1024, 1),
            "last_draw_ms": round(draw_ms, 2),
        }
        print(json.dumps(result, indent=2))
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
        return 0
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


if __name__ == "__main__":
    sys.exit(main())
