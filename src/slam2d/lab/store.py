"""The sweep result store: ``DIR/results.jsonl``, one checksummed JSON record per (config key, seed).

Each record is appended with a single ``write`` on an ``O_APPEND`` descriptor and ``fsync``-ed before the next.
:meth:`ResultStore.scan` checks every line; a line that cannot be used for ANY reason (partial, not JSON, nested too
deeply, an integer too long to convert, not a record, a wrong checksum, a duplicate) is a :class:`StoreProblem`;
:meth:`ResultStore.quarantine` moves such lines to ``DIR/quarantine.jsonl`` (never silently dropped) and rewrites the
store atomically. A ``results.jsonl`` that is not a regular file (e.g. a directory) is moved aside whole.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slam2d.io.atomic import atomic_write

STORE_FILE = "results.jsonl"
QUARANTINE_FILE = "quarantine.jsonl"


def _checksum(record: Mapping[str, Any]) -> str:
    body = {k: v for k, v in record.items() if k != "check"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:16]


@dataclass
class StoreProblem:
    """A store line that could not be used: its 1-based line number, why, and its raw text."""

    line: int
    reason: str
    text: str


class ResultStore:
    """Append-only JSONL store of run records keyed by (config key, seed) in ``directory``."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.path = self.directory / STORE_FILE
        self._fd: int | None = None

    # reading ------------------------------------------------------------------------------------------------
    def scan(self) -> tuple[dict[tuple[str, int], dict[str, Any]], list[StoreProblem]]:
        """All valid records (first one wins for a repeated (key, seed)) and every unusable line."""
        records: dict[tuple[str, int], dict[str, Any]] = {}
        problems: list[StoreProblem] = []
        if not self.path.exists() and not self.path.is_symlink():
            return records, problems
        if not self.path.is_file():
            problems.append(StoreProblem(0, f"{STORE_FILE} is not a regular file (a directory or a broken link)", ""))
            return records, problems
        raw = self.path.read_bytes()
        lines = raw.split(b"\n")
        # the text after the last newline is a partial record if non-empty (the writer always ends with "\n")
        for i, b in enumerate(lines, start=1):
            if not b.strip():
                continue
            text = b.decode("utf-8", errors="replace")
            if i == len(lines):
                problems.append(StoreProblem(i, "partial record (no end of line; the writer was interrupted)", text))
                continue
            try:
                rec = json.loads(text)
            except json.JSONDecodeError as e:
                problems.append(StoreProblem(i, f"not valid JSON ({e.msg} at column {e.colno})", text))
                continue
            except (ValueError, RecursionError, MemoryError) as e:  # e.g. a 5,000-digit integer, 200,000 '['
                problems.append(StoreProblem(i, f"unreadable JSON ({type(e).__name__}: {str(e)[:80]})", text))
                continue
            if not isinstance(rec, dict) or not isinstance(rec.get("key"), str) or not isinstance(rec.get("seed"), int):
                problems.append(StoreProblem(i, "not a run record (no 'key' and integer 'seed')", text))
                continue
            try:
                intact = rec.get("check") == _checksum(rec)
            except (ValueError, TypeError, RecursionError):
                intact = False
            if not intact:
                problems.append(StoreProblem(i, "checksum mismatch (the record was altered)", text))
                continue
            k = (rec["key"], rec["seed"])
            if k in records:
                problems.append(StoreProblem(i, f"duplicate record for config {k[0]} seed {k[1]}", text))
                continue
            records[k] = rec
        return records, problems

    def records(self) -> list[dict[str, Any]]:
        return list(self.scan()[0].values())

    # repairing ----------------------------------------------------------------------------------------------
    def quarantine(self, problems: Sequence[StoreProblem]) -> None:
        """Move the problem lines to ``quarantine.jsonl`` and rewrite the store without them (atomically). A store
        path that is not a regular file is renamed aside (``results.jsonl.quarantined-<time>``)."""
        if not problems:
            return
        stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        if not self.path.is_file():
            aside = self.path.with_name(f"{STORE_FILE}.quarantined-{stamp.replace(':', '')}")
            os.replace(self.path, aside)
            problems = [StoreProblem(0, f"{problems[0].reason}; moved to {aside.name}", "")]
            lines: list[bytes] = []
        else:
            lines = self.path.read_bytes().split(b"\n")
        bad = {p.line for p in problems}
        keep = [b for i, b in enumerate(lines, start=1) if b.strip() and i not in bad]
        with (self.directory / QUARANTINE_FILE).open("a") as q:
            for p in problems:
                q.write(json.dumps({"line": p.line, "reason": p.reason, "text": p.text, "moved_utc": stamp}) + "\n")
            q.flush()
            os.fsync(q.fileno())
        if lines:
            with atomic_write(self.path, "wb") as f:
                f.write(b"".join(b + b"\n" for b in keep))

    # writing ------------------------------------------------------------------------------------------------
    def open(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        new = not self.path.exists()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        if new:
            self._fsync_dir()

    def append(self, record: Mapping[str, Any]) -> None:
        """Append one record as one line: a single write on an O_APPEND descriptor, then fsync."""
        if self._fd is None:
            self.open()
        assert self._fd is not None
        rec = dict(record)
        rec["check"] = _checksum(rec)
        data = (json.dumps(rec, sort_keys=True, separators=(",", ":"), allow_nan=False) + "\n").encode()
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        os.fsync(self._fd)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _fsync_dir(self) -> None:
        fd = os.open(self.directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
