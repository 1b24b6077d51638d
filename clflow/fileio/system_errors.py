"""File-system errors as one line: which OSErrors are the file system refusing (not a bug),
and how to say so."""

from __future__ import annotations

import errno

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
