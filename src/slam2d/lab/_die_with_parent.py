"""Imported ONLY by the sweep's forkserver (``set_forkserver_preload``) and called by its workers: ask Linux to
kill this process when its parent dies (``prctl(PR_SET_PDEATHSIG, SIGKILL)``).

Without it, ``kill -9`` of a sweep leaves the forkserver and its workers running their jobs for minutes (and holding
the caller's pipes open). The chain is: sweep dies -> forkserver gets SIGKILL -> workers (children of the forkserver)
get SIGKILL -> the resource tracker sees its pipe close and exits. Elsewhere than Linux this does nothing.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Set the parent-death signal of this process to SIGKILL; exit at once if the parent is already gone."""
    if not sys.platform.startswith("linux"):
        return
    parent = os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # pragma: no cover - no libc prctl
        return
    if os.getppid() != parent or parent == 1:  # the parent died before the signal was armed
        os._exit(1)


die_with_parent()
