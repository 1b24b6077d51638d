"""What a file or folder holds, as a digest, and a file's fingerprint.

A digest (:func:`content_digest`) is a SHA-256 of the bytes, not of the place: moving or
copying a file keeps it. Each file is read once per process for a (size, mtime, ctime,
inode) it has (what hashing costs: docs/architecture.md, "Outputs"). A fingerprint (:func:`fingerprint`) is that stat
tuple: equal fingerprints of one path mean the file was not written since, because any
write moves its ctime, which no user call can set back.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: bookkeeping entries of clflow's in every folder it writes (the record, the writer's lock,
#: staging folders), which a folder's digest leaves out: writing there does not change it
BOOKKEEPING_PREFIX = ".clflow-"

_DIGESTS: dict[tuple, str] = {}  # (path, fingerprint) -> digest of a file already read


def fingerprint(path: str | os.PathLike) -> list[int]:
    """[size, mtime_ns, ctime_ns, inode, device] of ``path`` itself (a link is not followed)."""
    st = os.lstat(path)
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]


def content_digest(path: str | os.PathLike) -> str:
    """A SHA-256 of what ``path`` holds: a file's bytes; a folder's files by relative name
    and digest (clflow's bookkeeping left out); "missing" when there is nothing."""
    path = Path(path)
    if path.is_file():
        key = (str(path.resolve()), *fingerprint(path.resolve()))
        if key not in _DIGESTS:
            h = hashlib.sha256()
            with open(path, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
            _DIGESTS[key] = h.hexdigest()
        return _DIGESTS[key]
    if path.is_dir():
        h = hashlib.sha256()
        for entry in sorted(p for p in path.rglob("*") if p.is_file()):
            name = entry.relative_to(path)
            if not any(part.startswith(BOOKKEEPING_PREFIX) for part in name.parts):
                h.update(f"{name.as_posix()}={content_digest(entry)};".encode())
        return h.hexdigest()
    return "missing"


__all__ = ["BOOKKEEPING_PREFIX", "content_digest", "fingerprint"]
