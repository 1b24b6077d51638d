"""File I/O: atomic output (a file or folder is either complete or not there), user arrays
read with clear errors, file-system errors in one line (checks before the work: clflow.limits).

    with atomic_path("out/frames.npz") as tmp:   # tmp is in the same folder
        np.savez(tmp, x=x)                       # write however you like
    # now out/frames.npz exists, complete; on an exception nothing is left behind
    with atomic_dir("out/render") as tmp:        # a temporary folder next to out/render
        ...                                      # its entries move into out/render at the end
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

if TYPE_CHECKING:
    import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` if the block succeeds.

    The temporary name keeps ``path``'s suffix so writers that choose a format by the
    extension (numpy, OpenCV) behave as they would with ``path`` itself.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


#: OSError numbers that mean "the file system refused", not a bug: one line at the CLI.
FILE_SYSTEM_ERRNOS = frozenset(
    {
        errno.ENOSPC,
        errno.EDQUOT,
        errno.EROFS,
        errno.EACCES,
        errno.EPERM,
        errno.ENOTDIR,
        errno.EEXIST,
        errno.EISDIR,
        errno.ENOENT,
        errno.ENAMETOOLONG,
        errno.EFBIG,
    }
)


def describe_os_error(exc: OSError) -> str:
    """One line for a file-system OSError: the path, what went wrong, and for a full disk what to do."""
    where = f"{exc.filename}: " if exc.filename is not None else ""
    reason = (exc.strerror or str(exc)).lower()
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        reason += " (free some space or write elsewhere)"
    return where + reason


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder next to folder ``path``; if the block succeeds, move what it
    holds into ``path`` (replacing entries of the same name), else delete it. A failure
    leaves ``path`` as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        if not path.exists():
            tmp.chmod(0o777 & ~_umask())
            os.replace(tmp, path)
            return
        for entry in tmp.iterdir():
            target = path / entry.name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            os.replace(entry, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def load_arrays(path: str | os.PathLike, what: str = "array file") -> dict[str, np.ndarray]:
    """The arrays of an .npz (by name) or an .npy (as ``{"array": a}``), read in full; a file
    that is empty, truncated, not numpy's or holds Python objects is an InputError."""
    import zipfile
    import zlib

    import numpy as np

    from clflow.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    with open(path, "rb") as fh:
        head = fh.read(6)
    if not head:
        raise InputError(f"{path}: the {what} is empty (0 bytes)")
    if head[:2] != b"PK" and head != b"\x93NUMPY":
        raise InputError(f"{path}: not a numpy .npz/.npy {what}")
    try:
        if head == b"\x93NUMPY":
            return {"array": np.load(path, allow_pickle=False)}
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except ValueError as exc:
        if "pickle" in str(exc):  # npz: "pickled (object) data", npy: "allow_pickle=False"
            raise InputError(
                f"{path}: the {what} holds Python objects, not plain arrays; refusing to unpickle"
            ) from None
        raise InputError(f"{path}: damaged or truncated {what} ({exc})") from None
    except (EOFError, OSError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"{path}: damaged or truncated {what} ({type(exc).__name__}: {exc})") from None
