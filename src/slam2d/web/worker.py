"""One worker thread per page session: the session's library calls never run on the server's event loop.

Every call a session makes (building it, applying a command, stepping and drawing a frame) goes through its own
:class:`SessionWorker`, so a slow call (a JCBB search, an optimisation) delays only that session: the event loop
keeps serving every other tab, and answers signals (Ctrl+C) at once. The thread is a daemon, so a call still
running when the server stops never holds the process up; calls of one session run one at a time, in order.
"""

from __future__ import annotations

import asyncio
import queue
import threading
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


class SessionWorker:
    """A daemon thread running submitted calls in order; ``await worker.run(fn, *args)`` from the event loop."""

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[tuple[Callable[..., Any], tuple[Any, ...], asyncio.Future[Any]] | None] = \
            queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name=name, daemon=True)
        self._thread.start()

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        fut: asyncio.Future[T] = asyncio.get_running_loop().create_future()
        self._jobs.put((fn, args, fut))
        return await fut

    def close(self) -> None:
        """Stop after the calls already queued (does not wait)."""
        self._jobs.put(None)

    def _serve(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            fn, args, fut = job
            try:
                result = fn(*args)
            except BaseException as e:  # handed to the awaiting coroutine, which decides what to do with it
                _settle(fut, None, e)
            else:
                _settle(fut, result, None)


def _settle(fut: asyncio.Future[Any], result: Any, error: BaseException | None) -> None:
    def done() -> None:
        if fut.done():  # the awaiting task was cancelled (its connection closed)
            return
        if error is not None:
            fut.set_exception(error)
        else:
            fut.set_result(result)

    try:
        fut.get_loop().call_soon_threadsafe(done)
    except RuntimeError:  # the event loop has closed: nobody is waiting any more
        pass
