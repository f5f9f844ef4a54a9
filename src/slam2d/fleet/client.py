"""One request to a map server and its reply (for watchers: the lab, the benchmark, tests)."""

from __future__ import annotations

from typing import Any

from slam2d.fleet.protocol import decode, encode


class ServerUnavailable(OSError):
    """No reply from the map server in time."""


def request(endpoint: str, msg: dict[str, Any] | bytes, timeout_s: float = 3.0) -> dict[str, Any]:
    """Send ``msg`` (a message map, or raw bytes as they are) on a fresh DEALER and return the decoded reply."""
    import zmq

    sock: Any = zmq.Context.instance().socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    try:
        sock.connect(endpoint)
        sock.send(msg if isinstance(msg, bytes) else encode(msg))
        if not sock.poll(int(timeout_s * 1000)):
            raise ServerUnavailable(110, f"no reply from the map server within {timeout_s:g} s", endpoint)
        return decode(sock.recv())
    finally:
        sock.close(0)


def status(endpoint: str, *, full: bool = False, timeout_s: float = 3.0) -> dict[str, Any]:
    return request(endpoint, {"type": "status", "full": full}, timeout_s)
