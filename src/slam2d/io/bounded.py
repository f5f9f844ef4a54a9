"""Reading text inputs with bounded memory: files are read in chunks, with a cap on the file size and the line length.

The caps protect the machine from inputs that are not what they claim (``/dev/zero``, a binary file, a runaway log):
such an input fails within one chunk with an error naming the file (and line), instead of reading gigabytes.
Defaults: 2048 MB per file and 1,000,000 characters per line; raise them with ``SLAM2D_MAX_FILE_MB`` and
``SLAM2D_MAX_LINE_CHARS``. Only the standard library is used (every reader may import this module).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from typing import BinaryIO

CHUNK = 1 << 20
MAX_FILE_ENV = "SLAM2D_MAX_FILE_MB"
MAX_LINE_ENV = "SLAM2D_MAX_LINE_CHARS"
DEFAULT_MAX_FILE_MB = 2048.0
DEFAULT_MAX_LINE_CHARS = 1_000_000


def _env_number(name: str, default: float) -> float:
    raw = os.environ.get(name, "")
    if not raw:
        return default
    try:
        v = float(raw)
    except ValueError:
        raise ValueError(f"{name} must be a number (got {raw!r})") from None
    if not v > 0:
        raise ValueError(f"{name} must be > 0 (got {raw!r})")
    return v


def limits() -> tuple[int, int]:
    """(max file bytes, max line characters) from the environment or the defaults."""
    return (int(_env_number(MAX_FILE_ENV, DEFAULT_MAX_FILE_MB) * 2**20),
            int(_env_number(MAX_LINE_ENV, DEFAULT_MAX_LINE_CHARS)))


def iter_lines(path: str | os.PathLike[str], error: type[Exception] = ValueError, *, encoding: str = "utf-8",
               errors: str = "replace", max_bytes: int | None = None, max_line: int | None = None,
               opener: Callable[[str], BinaryIO] | None = None) -> Iterator[str]:
    """Lines of a text file (without line ends), read in 1 MB chunks. Raises ``error`` naming the file when it is
    larger than ``max_bytes`` and ``file:line`` when a line is longer than ``max_line`` characters; with
    ``errors="strict"`` a byte sequence that is not ``encoding`` raises ``error`` naming ``file:line``.
    ``opener`` (e.g. ``bz2.open``) reads a compressed file: the caps then count decompressed bytes, so a
    decompression bomb stops within one chunk past the cap."""
    name = os.fspath(path)
    cap_bytes, cap_line = limits()
    max_bytes = cap_bytes if max_bytes is None else max_bytes
    max_line = cap_line if max_line is None else max_line
    total = 0
    lineno = 0
    pending = b""
    with (open(name, "rb") if opener is None else opener(name)) as fh:
        while True:
            chunk = fh.read(CHUNK)
            total += len(chunk)
            if total > max_bytes:
                raise error(f"{name}: larger than {max_bytes / 2**20:g} MB (set {MAX_FILE_ENV} to read it)")
            if not chunk:
                break
            parts = (pending + chunk).split(b"\n")
            pending = parts.pop()
            for raw in parts:
                lineno += 1
                yield _decode(raw, name, lineno, error, encoding, errors, max_line)
            if len(pending) > max_line:
                raise error(f"{name}:{lineno + 1}: line longer than {max_line} characters (not a text file of this "
                            f"format? set {MAX_LINE_ENV} to read it)")
    if pending:
        yield _decode(pending, name, lineno + 1, error, encoding, errors, max_line)


def _decode(raw: bytes, name: str, lineno: int, error: type[Exception], encoding: str, errors: str,
            max_line: int) -> str:
    if len(raw) > max_line:
        raise error(f"{name}:{lineno}: line longer than {max_line} characters (not a text file of this format? "
                    f"set {MAX_LINE_ENV} to read it)")
    try:
        return raw.decode(encoding, errors).rstrip("\r")
    except UnicodeDecodeError as e:
        raise error(f"{name}:{lineno}: not {encoding} text ({e.reason} at column {e.start + 1})") from None


def read_lines(path: str | os.PathLike[str], error: type[Exception] = ValueError, **kw: object) -> list[str]:
    """All lines of a text file via :func:`iter_lines` (same caps and errors)."""
    return list(iter_lines(path, error, **kw))  # type: ignore[arg-type]
