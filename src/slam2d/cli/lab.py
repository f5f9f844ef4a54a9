"""``slam2d lab``: serve the interactive web lab (one page per lesson chapter and the live simulator)."""

from __future__ import annotations

import argparse
import sys
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser("lab", help="serve the interactive web lab (open the printed URL in a browser)",
                       description="Serve the interactive web lab: live simulations of every chapter, drawn in the "
                                   "browser from numbers the library computes. Binds 127.0.0.1 unless told otherwise.")
    p.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="also accept pages served from ORIGIN, e.g. https://lab.example.org (repeatable); "
                        "by default only loopback origins may use the lab")
    p.set_defaults(func=cmd)


def cmd(args: argparse.Namespace) -> int:
    if not 0 < args.port < 65536:
        raise ValueError(f"--port must be in 1..65535 (got {args.port})")
    try:
        from slam2d.web.app import serve
    except ImportError as e:
        raise ValueError(f"the web lab needs the 'web' extra (pip install 'slam2d[web]'): {e}") from None
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"slam2d lab: warning: binding {args.host} exposes the lab to other machines", file=sys.stderr)
    # "serving on" only once the port is bound; a busy port is one error line
    serve(args.host, args.port, allow_origins=frozenset(args.allow_origin),
          announce=lambda url: print(f"slam2d lab: serving on {url}  (Ctrl+C to stop)", flush=True))
    return 0
