"""Limits checked before long work starts: the predicted output size (a limit the user
raises with ``--max-output-gb``), the disk's free space and the machine's memory.

Sizes are bytes; the predictions are upper bounds (uncompressed), so a run that passes
never stops half-way for these reasons.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from clflow.errors import InputError

#: Default of the commands' --max-output-gb (GB = 1e9 bytes).
DEFAULT_MAX_OUTPUT_GB = 10.0
#: Reals one simulated particle-frame holds in memory: x, v (3), F (9), plastic (1).
TRAJECTORY_REALS = 16
#: Free bytes below which a failed write is put down to a full disk.
LOW_DISK_BYTES = 1 << 20


def format_bytes(n: float) -> str:
    """``n`` bytes as B, kB, MB, GB or TB (powers of 1000)."""
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000:
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} TB"


def format_duration(seconds: float) -> str:
    """``seconds`` as s, min or h, to 2-3 significant digits."""
    if seconds < 120:
        return f"{seconds:.2g} s" if seconds < 100 else f"{seconds:.0f} s"  # not 1.1e+02 s
    if seconds < 7200:
        return f"{seconds / 60:.3g} min"
    return f"{seconds / 3600:.3g} h"


def _nearest_existing(path: Path) -> Path:
    """The nearest of ``path`` and its parents that exists; InputError for a link to nothing
    on the way (a write there would fail after the work)."""
    path = Path(os.path.abspath(path))
    while not path.exists():
        if path.is_symlink():
            raise InputError(dangling_link(path))
        path = path.parent
    return path


def dangling_link(path: Path) -> str:
    """The message for ``path``, a symbolic link to something that does not exist."""
    return f"{path} is a symbolic link to {os.readlink(path)}, which does not exist: make it, or write elsewhere (-o)"


def _writable(folder: Path) -> str:
    """Why files cannot be made in existing ``folder`` ('' when they can): a probe file is
    made and removed, since permission bits say nothing of /proc, a full quota or a
    read-only mount."""
    if not os.access(folder, os.W_OK | os.X_OK):
        return "read-only file system or no permission"
    try:
        fd, probe = tempfile.mkstemp(prefix=".clflow-probe-", dir=folder)
    except OSError as exc:
        return (exc.strerror or str(exc)).lower()
    os.close(fd)
    os.unlink(probe)
    return ""


def check_output_file(path: str | os.PathLike, what: str = "output file") -> None:
    """Raise InputError unless file ``path`` can be written: not a folder, in a folder that
    exists or can be made and is writable. Creates nothing lasting: call it before the work."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{what} {path} is a folder, not a file")
    existing = _nearest_existing(path.parent)
    if not existing.is_dir():
        raise InputError(f"{what} {path}: {existing} is a file, not a folder")
    reason = _writable(existing)
    if reason:
        raise InputError(f"{what} {path}: {existing} is not writable ({reason})")


def check_output(
    path: str | os.PathLike, nbytes: int = 0, max_gb: float = DEFAULT_MAX_OUTPUT_GB, what: str = "", hint: str = ""
) -> None:
    """Raise InputError unless folder ``path`` exists or can be made and is writable, and
    ``nbytes`` (the predicted output: ``what``) is within ``max_gb`` and the disk's free
    space; ``hint`` says how to write less. Creates nothing lasting: call it before the work."""
    path = Path(path)
    existing = _nearest_existing(path)
    if not existing.is_dir():
        where = "" if existing == Path(os.path.abspath(path)) else f": {existing}"
        raise InputError(f"output folder {path}{where} is a file, not a folder")
    reason = _writable(existing)
    if reason:
        raise InputError(f"output folder {path}: {existing} is not writable ({reason})")
    size = f"would write up to {format_bytes(nbytes)} ({what})"
    if nbytes > max_gb * 1e9:
        raise InputError(f"{path}: {size}, more than --max-output-gb {max_gb:g}; raise it{hint and ' or '}{hint}")
    free = shutil.disk_usage(existing).free
    if nbytes > free:
        raise InputError(
            f"{path}: {size}, the disk has {format_bytes(free)} free; free some space{hint and ' or '}{hint}"
        )


def why_not_written(path: str | os.PathLike) -> str:
    """Why a writer that reports only failure (OpenCV) could not write ``path``, if its
    folder or disk is the cause; else ''."""
    folder = _nearest_existing(Path(path).parent)
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"{folder} is not writable (read-only file system or no permission)"
    free = shutil.disk_usage(folder).free
    if free < LOW_DISK_BYTES:
        return f"no space left on the device ({format_bytes(free)} free)"
    return ""


def physical_memory() -> int:
    """Bytes of RAM of this machine."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_memory(nbytes: int, what: str, hint: str) -> None:
    """Raise InputError if ``nbytes`` (held in memory for ``what``) exceed the machine's RAM."""
    ram = physical_memory()
    if nbytes > ram:
        raise InputError(
            f"{what} would hold about {format_bytes(nbytes)} in memory, the machine has {format_bytes(ram)}; {hint}"
        )
