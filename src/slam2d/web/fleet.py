"""The lab's fleet view: ``/fleet`` (the page) and ``/api/fleet?server=tcp://127.0.0.1:PORT`` (a snapshot asked of
a running ``slam2d map-server``). The lab only watches: it sends one ``status`` request per poll and nothing else.

Only map servers on this machine are asked (a loopback host), so a page cannot make the lab connect elsewhere;
the default address is ``$SLAM2D_FLEET_SERVER`` or ``tcp://127.0.0.1:5555``.
"""

from __future__ import annotations

import asyncio
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from fastapi import FastAPI
from fastapi.responses import FileResponse, JSONResponse

STATIC = Path(__file__).parent / "static"
_ADDRESS = re.compile(r"^tcp://(127\.\d{1,3}\.\d{1,3}\.\d{1,3}|localhost|\[::1\]):(\d{1,5})$")


def default_server() -> str:
    return os.environ.get("SLAM2D_FLEET_SERVER", "tcp://127.0.0.1:5555")


def snapshot(server: str) -> dict[str, Any]:
    """The server's status as JSON-ready lists (positions rounded to cm)."""
    from slam2d.fleet.client import status

    s = status(server, timeout_s=2.0)
    drones = []
    for d in s["drones"]:
        xy = np.frombuffer(d["poses"], "<f4").reshape(-1, 2)
        drones.append({k: d[k] for k in ("drone", "keyframes", "acked_seq", "connected", "idle_s", "bytes_in",
                                         "bytes_out")} | {"xy": np.round(xy, 2).tolist()})
    return {"server": server, "drones": drones, "loops": s["loops"], "errors": s["errors"],
            "solves": s["solves"], "uptime_s": s["uptime_s"]}


def register_fleet(app: FastAPI) -> None:
    @app.get("/fleet")
    async def fleet_page() -> FileResponse:
        return FileResponse(STATIC / "fleet.html")

    @app.get("/api/fleet")
    async def fleet_api(server: str | None = None) -> JSONResponse:
        addr = server or default_server()
        m = _ADDRESS.match(addr)
        if m is None or not 0 < int(m.group(2)) < 65536:
            return JSONResponse({"error": f"server must be tcp://127.0.0.1:PORT (a map server on this machine); "
                                          f"got {addr!r}"}, status_code=400)
        try:
            return JSONResponse(await asyncio.to_thread(snapshot, addr))
        except ImportError as e:
            return JSONResponse({"error": f"the fleet view needs pyzmq and msgpack ({e.name} is missing): "
                                          "pip install 'slam2d[fleet]'"}, status_code=503)
        except OSError as e:
            return JSONResponse({"error": f"no map server answers at {addr} ({e.strerror or e}); start one with "
                                          "'slam2d map-server --db MAP.db'"}, status_code=503)
        except ValueError as e:  # a reply that is not our protocol
            return JSONResponse({"error": f"{addr}: {e}"}, status_code=502)
