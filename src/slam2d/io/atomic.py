"""Writing outputs without ever destroying what was there: a temporary file beside the target, then a rename.

Every command that writes goes through :func:`atomic_write` (an open file) or :func:`atomic_path` (a temporary
path for writers that want a file name, e.g. matplotlib). The temporary file lives in the target's directory
(``.NAME.XXXX.tmp``) so the final ``os.replace`` is atomic on POSIX: readers see the old file or the complete new
one, and a failed write (full disk, exception, Ctrl-C) leaves the old file untouched and removes the temporary.

Targets that exist but are not regular files (``/dev/null``, ``/dev/full``, a FIFO) are written in place: there is
nothing to protect and renaming over a device would replace it.

:func:`check_output` validates an output path before long work starts, and :func:`refuse_overwrite_input` refuses
an output that is one of the command's inputs (unless forced).
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

PathLike = str | os.PathLike[str]


def _is_special(p: Path) -> bool:
    try:
        st = os.stat(p)
    except OSError:
        return False
    return not stat.S_ISREG(st.st_mode) and not stat.S_ISDIR(st.st_mode)


def _final_mode(p: Path) -> int:
    """The mode the new file gets: the old file's, else the usual 0o666 minus the umask."""
    try:
        return stat.S_IMODE(os.stat(p).st_mode)
    except OSError:
        mask = os.umask(0)
        os.umask(mask)
        return 0o666 & ~mask


def check_output(path: PathLike, what: str = "output") -> Path:
    """Fail now (OSError naming the path) if ``path`` cannot be written later: it is a directory, or its nearest
    existing ancestor is not a writable directory. Missing parent directories are fine (they are created)."""
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory", f"{what} {p}")
    if _is_special(p):
        return p
    parent = p.parent
    while not parent.exists():
        if parent == parent.parent:
            break
        parent = parent.parent
    if not parent.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, f"{parent} is not a directory", f"{what} {p}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(errno.EACCES, f"directory {parent} is not writable", f"{what} {p}")
    if parent == p.parent:  # it exists: try a file there (root passes os.access where writes fail: /proc, read-only
        try:  # mounts), so that the error comes before the work, naming the option
            tempfile.TemporaryFile(dir=parent).close()
        except OSError as e:
            raise PermissionError(e.errno or errno.EACCES, f"cannot create a file in {parent} ({e.strerror})",
                                  f"{what} {p}") from None
    return p


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def refuse_overwrite_input(inputs: Iterable[PathLike | None], outputs: Iterable[tuple[str, PathLike | None]],
                           force: bool = False) -> None:
    """ValueError if an output is one of the inputs (unless ``force``) or two outputs are the same file.

    ``outputs`` are (option name, path) pairs so the message can name the option."""
    ins = [Path(i) for i in inputs if i is not None]
    outs = [(name, Path(o)) for name, o in outputs if o is not None]
    for k, (name, o) in enumerate(outs):
        if _is_special(o):
            continue
        for other_name, other in outs[:k]:
            if _same(o, other):
                raise ValueError(f"{name} {o}: same file as {other_name}")
        if not force:
            for i in ins:
                if _same(o, i):
                    raise ValueError(f"{name} {o}: would overwrite the input {i} (pass --force to allow it)")


@contextlib.contextmanager
def _naming(p: Path) -> Iterator[None]:
    """OSErrors without a file name (ENOSPC from write, EIO from fsync) get the target's name."""
    try:
        yield
    except OSError as e:
        if e.filename is None and e.errno is not None:
            raise type(e)(e.errno, e.strerror or str(e), str(p)) from e
        raise


def _tmp_beside(p: Path, suffix: str = ".tmp") -> tuple[int, Path]:
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=suffix, dir=p.parent)
    return fd, Path(tmp)


def _commit(tmp: Path, p: Path, mode: int) -> None:
    os.chmod(tmp, mode)
    os.replace(tmp, p)
    with contextlib.suppress(OSError):  # make the rename durable; not every file system lets us open a directory
        dfd = os.open(p.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` (same extension, so writers that infer the format from it still work);
    renamed onto ``path`` when the block ends without an exception, removed otherwise."""
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory", str(p))
    if _is_special(p):
        yield p
        return
    mode = _final_mode(p)
    fd, tmp = _tmp_beside(p, f".tmp{p.suffix}")
    os.close(fd)
    try:
        with _naming(p):
            yield tmp
            _commit(tmp, p, mode)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


@contextlib.contextmanager
def atomic_write(path: PathLike, mode: str = "w", *, encoding: str | None = "utf-8") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing (``mode`` "w" or "wb"); flushed, fsync-ed and renamed
    onto ``path`` when the block ends without an exception, removed otherwise."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb' (got {mode!r})")
    enc = None if "b" in mode else encoding
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory", str(p))
    if _is_special(p):
        with _naming(p), open(p, mode, encoding=enc) as fh:
            yield fh
        return
    final_mode = _final_mode(p)
    fd, tmp = _tmp_beside(p)
    try:
        with _naming(p), os.fdopen(fd, mode, encoding=enc) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        _commit(tmp, p, final_mode)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_text_atomic(path: PathLike, text: str) -> Path:
    """``Path.write_text`` that never leaves a truncated file (see :func:`atomic_write`)."""
    with atomic_write(path, "w") as fh:
        fh.write(text)
    return Path(path)


@contextlib.contextmanager
def exclusive(path: str | Path, held: str) -> Iterator[None]:
    """Hold an advisory lock on ``path`` (created if missing) for the block, without waiting: when another process
    holds it, ``ValueError(f"{held} (lock {name} is held)")``. The lock goes with the process: a crash releases it."""
    import fcntl

    path = Path(path)
    with path.open("a") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ValueError(f"{held} (lock {path.name} is held)") from None
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
