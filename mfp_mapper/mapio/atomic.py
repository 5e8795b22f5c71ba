"""Atomic file writes: a reader sees the old file or the whole new one, never a part.

A write goes to a temporary file next to the target, named
``.<target name>.<pid>.<random>.mfp-tmp``, which is flushed and renamed over the target. A
write interrupted hard (power loss, SIGKILL) leaves such a file behind; the next write to
the same target removes the ones of processes no longer running, and a program can sweep a
folder at start with ``remove_stale_temp_files``. New files get the permissions the user's
umask gives (``0666 & ~umask``); an existing target keeps its mode. When the target is a
symlink, the file it points to is replaced and the link kept.
"""

from __future__ import annotations

import contextlib
import glob
import os
import secrets
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

TEMP_SUFFIX = ".mfp-tmp"
"""Ending of every temporary file of an atomic write."""

_active: set[str] = set()  # temporary files this process is writing now
_active_lock = threading.Lock()


def _umask() -> int:
    """The process's umask, read without changing it where the system allows."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)  # elsewhere: read by setting (briefly) and restoring
    os.umask(mask)
    return mask


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _is_stale(path: Path) -> bool:
    """Whether ``path`` (a temporary file of ours) belongs to no write in progress."""
    parts = path.name[: -len(TEMP_SUFFIX)].rsplit(".", 2)
    if len(parts) != 3 or not parts[1].isdigit():
        return False  # not a name this module makes
    pid = int(parts[1])
    if pid == os.getpid():
        with _active_lock:
            return str(path) not in _active
    return not _pid_alive(pid)


def remove_stale_temp_files(folder: str | Path, target_name: str | None = None) -> list[Path]:
    """Remove the temporary files of interrupted atomic writes in ``folder`` (only those
    of ``target_name`` when given); returns the paths removed. Files of writes still in
    progress (this process or another running one) are left alone."""
    name = glob.escape(target_name) if target_name else ""
    pattern = f".{name}.*{TEMP_SUFFIX}" if target_name else f".*{TEMP_SUFFIX}"
    removed = []
    with contextlib.suppress(OSError):
        for path in Path(folder).glob(pattern):
            if _is_stale(path):
                with contextlib.suppress(OSError):
                    path.unlink()
                    removed.append(path)
    return removed


@contextmanager
def atomic_output(path: str | Path) -> Iterator[BinaryIO]:
    """A binary file to write ``path`` through: a temporary file in the same folder,
    flushed to disk and renamed over ``path`` when the block ends; removed on error."""
    target = Path(os.path.realpath(path))  # a symlink: replace the file it points to
    target.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temp_files(target.parent, target.name)
    tmp = target.parent / f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}{TEMP_SUFFIX}"
    try:
        mode = target.stat().st_mode & 0o7777
    except OSError:
        mode = 0o666 & ~_umask()
    with _active_lock:
        _active.add(str(tmp))
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            with os.fdopen(fd, "wb") as out:
                os.fchmod(out.fileno(), mode)
                yield out
                out.flush()
                os.fsync(out.fileno())
            os.replace(tmp, target)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    finally:
        with _active_lock:
            _active.discard(str(tmp))


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_output(path) as f:
        f.write(text.encode("utf-8"))
