"""``slam2d lab``: serve the interactive web lab (one page per lesson chapter and the live simulator)."""

from __future__ import annotations

import argparse
import errno
import os
import socket
import sys
import urllib.parse
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


def port_problem(host: str, port: int) -> str | None:
    """Why ``host:port`` cannot be served (one line), or None when it is free. Checked by binding it briefly."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # what uvicorn sets: TIME_WAIT does not count
        try:
            s.bind((host, port))
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                return (f"port {port} is already in use (another lab or server?); choose another with --port N, "
                        f"e.g. `slam2d lab --port {port + 10}` or `make run PORT={port + 10}`")
            return f"cannot listen on {host}:{port}: {e.strerror or e}"
    return None


def cmd(args: argparse.Namespace) -> int:
    if not 0 < args.port < 65536:
        raise ValueError(f"--port must be in 1..65535 (got {args.port})")
    for origin in args.allow_origin:  # compared with the browser's Origin header: scheme://host[:port], nothing more
        u = urllib.parse.urlsplit(origin)
        if u.scheme not in ("http", "https") or not u.hostname or u.path or u.query or u.fragment:
            raise ValueError(f"--allow-origin: expected an origin such as https://lab.example.org (scheme://host"
                             f"[:port], no path), got {origin!r}")
    try:
        from slam2d.web.app import serve
    except ImportError as e:
        raise ValueError(f"the web lab needs the 'web' extra (pip install 'slam2d[web]'): {e}") from None
    problem = port_problem(args.host, args.port)
    if problem is not None:
        print(f"slam2d lab: {problem}", file=sys.stderr)
        return 2
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"slam2d lab: warning: binding {args.host} exposes the lab to other machines", file=sys.stderr)
    try:
        # "serving on" only once the port is bound; a busy port is one error line
        serve(args.host, args.port, allow_origins=frozenset(args.allow_origin),
              announce=lambda url: print(f"slam2d lab: serving on {url}  (Ctrl+C to stop)", flush=True))
    except KeyboardInterrupt:
        pass
    # the server has stopped and holds nothing to save: skip the interpreter's slow teardown of ~1,000 modules
    # (about a second), so Ctrl+C ends the lab at once
    print("slam2d lab: stopped", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(0)
