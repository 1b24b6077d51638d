"""The writer's lock of a folder: one clflow run writes a folder at a time.

A run holds ``FOLDER/.clflow-lock`` with flock(2) while it writes there (a command: for its
whole run; a single file's write: for its move and record). The kernel drops the lock when
the holder ends, however it ends (kill -9 included), and a holder on another machine of a
network file system holds it there too, so a lock never outlives its run and needs no
process id to judge. A second writer is refused in one line naming the holder, or waits for
it (:func:`wait_for_writers`, ``clflow --wait``). The file exists only while held: the
holder removes it on release, and a new holder checks that the path it locked is still the
file there (else it locks again), so a holder that has just removed it cannot let two in.

Within one process the lock is re-entrant (a command's run holds it, and its writes there
take it again). A file system without flock (some NFS mounts without a lock manager) is
written unlocked, with one warning: two runs into one folder are then not kept apart.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import json
import logging
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

from clflow.errors import InputError

LOCK_NAME = ".clflow-lock"
#: errno of a file system that has no flock: written unlocked
_NO_LOCKS = frozenset({errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS})
#: errno of a folder a reader may not write in (a read-only result): read unlocked
_READ_ONLY = frozenset({errno.EACCES, errno.EPERM, errno.EROFS})

log = logging.getLogger("clflow.fileio")
_wait = False


def wait_for_writers(wait: bool) -> None:
    """Whether a folder another clflow run is writing is waited for (True) or refused (False, the default)."""
    global _wait
    _wait = wait


class FolderBusy(InputError):
    """Another clflow run holds the folder's lock."""

    def __init__(self, folder: Path, holder: dict, shared: bool):
        doing = "read" if holder.get("shared") else "written"
        who = (
            f" (`{holder['command']}`, pid {holder['pid']} on {holder['host']}, since {holder['since']})"
            if {"command", "pid", "host", "since"} <= holder.keys()
            else ""
        )
        super().__init__(
            f"{folder} is being {doing} by another clflow run{who}: let it finish, "
            f"{'' if shared else 'write elsewhere (-o), '}or run with `clflow --wait ...` to wait for it"
        )


@dataclasses.dataclass
class _Hold:
    fd: int | None  # None: the file system has no locks, or a reader may not write there
    shared: bool
    count: int = 1


_HELD: dict[tuple[int, int], _Hold] = {}  # (device, inode) of a folder -> this process's hold
_HELD_LOCK = threading.RLock()


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, *, shared: bool = False) -> Iterator[bool]:
    """Hold existing ``folder``'s lock (``shared``: a reader's, which writers wait for and
    other readers share) until the block ends; yields whether this is the process's first
    hold of it (the place to finish what a dead run left). Raises :class:`FolderBusy`
    when another run holds it and :func:`wait_for_writers` is off."""
    folder = Path(folder)
    st = os.stat(folder)
    key = (st.st_dev, st.st_ino)
    with _HELD_LOCK:
        hold = _HELD.get(key)
        first = hold is None
        if first:
            hold = _HELD[key] = _Hold(_acquire(folder, shared), shared, 0)
        elif hold.shared and not shared and hold.fd is not None:  # a reader that now writes
            _convert(folder, hold.fd)
            hold.shared = False
        hold.count += 1
    try:
        yield first
    finally:
        with _HELD_LOCK:
            hold.count -= 1
            if hold.count == 0:
                del _HELD[key]
                _release(folder, hold)


def _acquire(folder: Path, shared: bool) -> int | None:
    path = folder / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            if shared and exc.errno in _READ_ONLY:
                return None
            raise
        try:
            _lock(folder, fd, fcntl.LOCK_SH if shared else fcntl.LOCK_EX)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in _NO_LOCKS:
                raise
            log.warning(
                "%s: this file system has no locks (%s); two runs writing it at once are not kept apart",
                folder,
                exc.strerror,
            )
            return None
        except BaseException:
            os.close(fd)
            raise
        try:
            current = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)  # its last holder removed it between our open and our lock: lock the new one
    _describe(fd, shared)
    return fd


def _lock(folder: Path, fd: int, mode: int) -> None:
    """flock ``fd``; refuse, or wait, when another run holds it."""
    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
        return
    except BlockingIOError:
        holder = _holder(fd)
        if not _wait:
            raise FolderBusy(folder, holder, mode == fcntl.LOCK_SH) from None
    log.warning("%s is in use by another clflow run (%s): waiting for it", folder, holder.get("command", "unknown"))
    fcntl.flock(fd, mode)


def _convert(folder: Path, fd: int) -> None:
    """A shared hold made exclusive (refused, or waited for, while other readers hold it)."""
    _lock(folder, fd, fcntl.LOCK_EX)
    _describe(fd, shared=False)


def _describe(fd: int, shared: bool) -> None:
    """Say in the lock file who holds it, for the message of a refused writer."""
    holder = {
        "command": " ".join(["clflow" if i == 0 else a for i, a in enumerate(sys.argv)]),
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "since": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "shared": shared,
    }
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)


def _holder(fd: int) -> dict:
    """Who holds the lock, as they wrote it (a holder that has just taken it writes within
    milliseconds: read again for up to 50 ms; {} when it still says nothing)."""
    for _ in range(10):
        try:
            holder = json.loads(os.pread(fd, 1 << 16, 0))
            if isinstance(holder, dict):
                return holder
        except (OSError, ValueError):
            pass
        time.sleep(0.005)
    return {}


def _release(folder: Path, hold: _Hold) -> None:
    """Remove the lock file while it is ours alone (a reader first makes its hold exclusive,
    which fails while other readers hold it: they remove it), then drop the lock."""
    if hold.fd is None:
        return
    try:
        if hold.shared:
            fcntl.flock(hold.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        if os.stat(folder / LOCK_NAME).st_ino == os.fstat(hold.fd).st_ino:
            os.unlink(folder / LOCK_NAME)
    except OSError:  # other readers hold it, or it is gone: theirs to remove
        pass
    finally:
        os.close(hold.fd)


__all__ = ["LOCK_NAME", "FolderBusy", "folder_lock", "wait_for_writers"]
