"""Writing outputs: atomically (a file or folder is either complete or not there), and only
over what clflow wrote (each folder's written-record).

    with atomic_path("out/frames.npz") as tmp:   # tmp is in the same folder
        np.savez(tmp, x=x)                       # write however you like
    # now out/frames.npz exists, complete; on an exception nothing is left behind
    with atomic_dir("out/render") as tmp:        # a temporary folder next to out/render
        ...                                      # its entries move into out/render at the end
"""

from __future__ import annotations

import contextlib
import glob
import os
import re
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import Iterator

# a temporary of atomic_path / atomic_dir: ".<stem>.<pid>.<mkstemp's random part>.tmp<suffix>"
#: the signals a result's last moves hold back (Ctrl-C, and what schedulers send)
HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)
_TEMPORARY = re.compile(r"^\..+\.(?P<pid>\d+)\.[A-Za-z0-9_]+\.tmp")


def _temporary_prefix(path: Path, stem: str) -> str:
    """The prefix of this process's temporaries for ``path`` (``.<stem>.<pid>.``); first
    removes the temporaries that killed processes left in the same folder (any target's, their
    pid no longer running), so a crash's leftovers go with clflow's next write there. A staging
    folder of this process's :func:`atomic_dir` holds none: not searched (one listing per
    file would make n frames O(n^2))."""
    for leftover in () if _staged(path.parent) else path.parent.glob(".*.tmp*"):
        match = _TEMPORARY.match(leftover.name)
        if match and not _running(int(match["pid"])):
            if leftover.is_dir() and not leftover.is_symlink():
                shutil.rmtree(leftover, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    leftover.unlink()
    return f".{stem}.{os.getpid()}."


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _creating(path: Path, make):
    """``make()`` (a mkstemp/mkdtemp call next to ``path``), its OSError naming ``path``
    itself rather than the temporary name it tried."""
    try:
        return make()
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write here ({(exc.strerror or str(exc)).lower()})", str(path)) from None


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` if the block succeeds
    and list it in its folder's written-record (:data:`WRITTEN_RECORD`).

    The temporary name keeps ``path``'s suffix so writers that choose a format by the
    extension (numpy, OpenCV) behave as they would with ``path`` itself.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix = _temporary_prefix(path, path.stem)
    fd, tmp = _creating(path, lambda: tempfile.mkstemp(prefix=prefix, suffix=f".tmp{path.suffix}", dir=path.parent))
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield Path(tmp)
        if _staged(path.parent):  # atomic_dir records its whole result at once
            os.replace(tmp, path)
            return
        digest = content_digest(tmp)
        with _record_lock(path.parent):
            os.replace(tmp, path)
            record = _written_record(path.parent)
            record["files"][path.name] = digest
            _write_record(path.parent, record)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


#: files larger than this are known by name and size, not read whole, in content digests
DIGEST_READ_BYTES = 64 * 2**20
_DIGESTS: dict[tuple, str] = {}  # (path, size, mtime) -> digest of a file already read


def content_digest(path: str | os.PathLike) -> str:
    """A SHA-256 of what ``path`` holds, not of where it lies: a file's bytes (a file over
    DIGEST_READ_BYTES: its size), a folder's files by relative name and digest, "missing"
    when there is nothing. Moving or copying a run's inputs keeps their digests."""
    import hashlib

    path = Path(path)
    h = hashlib.sha256()
    if path.is_file():
        st = path.stat()
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
        if key not in _DIGESTS:
            if st.st_size > DIGEST_READ_BYTES:
                h.update(f"size:{st.st_size}".encode())
            else:
                with open(path, "rb") as fh:
                    for block in iter(lambda: fh.read(1 << 20), b""):
                        h.update(block)
            _DIGESTS[key] = h.hexdigest()
        return _DIGESTS[key]
    if path.is_dir():
        for entry in sorted(p for p in path.rglob("*") if p.is_file()):
            h.update(f"{entry.relative_to(path).as_posix()}={content_digest(entry)};".encode())
        return h.hexdigest()
    return "missing"


#: each output folder's record of the files clflow wrote there: {"files": {relative path:
#: content digest}, "source": the folder it was derived from, relative (render4d's)}. A
#: command replaces or removes an entry only when this record proves clflow wrote all of it.
WRITTEN_RECORD = ".clflow-written.json"


def _written_record(folder: Path) -> dict:
    import json

    try:
        record = json.loads((folder / WRITTEN_RECORD).read_text())
    except (OSError, ValueError):
        return {"files": {}}
    ok = isinstance(record, dict) and isinstance(record.get("files"), dict)
    return record if ok else {"files": {}}


def _unowned_files(folder: Path, entry: Path) -> list[Path]:
    """The files of ``entry`` (a file, or a folder's files at any depth) in ``folder`` that
    no written-record (``folder``'s or one between it and the file) lists with its content."""
    files = (
        [entry] if not entry.is_dir() or entry.is_symlink() else sorted(p for p in entry.rglob("*") if not p.is_dir())
    )
    records: dict[Path, dict] = {}
    unowned = []
    for file in files:
        if file.name == WRITTEN_RECORD:
            continue
        place, owned = file.parent, False
        while not owned:
            listed = records.setdefault(place, _written_record(place))["files"]
            name = file.relative_to(place).as_posix()
            owned = name in listed and not file.is_symlink() and listed[name] == content_digest(file)
            if place == folder:
                break
            place = place.parent
        if not owned:
            unowned.append(file)
    return unowned


def derived_folders(path: Path) -> list[Path]:
    """The folders in ``path`` that clflow derived from what ``path`` holds (their written-record
    names ``path`` as its source, e.g. ``clflow render4d SIM -o SIM/mine``)."""
    if not path.is_dir():
        return []
    return [
        child
        for child in sorted(path.iterdir())
        if child.is_dir()
        and isinstance(source := _written_record(child).get("source"), str)
        and (child / source).resolve() == path.resolve()
    ]


def check_output_folder(path: str | os.PathLike, entries: tuple[str, ...], inputs=(), *, derived: bool = False) -> None:
    """Refuse (InputError, one line) before any work a write into folder ``path`` that would
    replace or remove what clflow did not write: ``entries`` are glob patterns of every entry
    the command writes or replaces there (``derived``: also the folders clflow derived from
    the earlier result); an entry's files must all be listed, with their content, in a
    written-record, and none of ``inputs`` (the run's input files) may lie in one."""
    from clflow.errors import InputError

    path = Path(path)
    if not path.is_dir():
        return
    targets = {entry for pattern in entries for entry in path.glob(pattern)}
    targets = sorted(targets | set(derived_folders(path) if derived else []))
    for given in inputs:
        source = Path(given).resolve()
        for target in targets:
            if source == target.resolve():
                raise InputError(f"{given} is an input of this run and one of its outputs: write elsewhere (-o)")
            if target.resolve() in source.parents:
                raise InputError(
                    f"{given} is an input of this run and lies in {target}, which this run replaces: write "
                    f"elsewhere (-o) or move the input"
                )
    unowned = [file for target in targets for file in _unowned_files(path, target)]
    if unowned:
        names = ", ".join(str(f.relative_to(path)) for f in unowned[:3]) + (
            f" and {len(unowned) - 3} more" if len(unowned) > 3 else ""
        )
        raise InputError(
            f"{path} holds {names}, which clflow did not write (or which changed since) and this run would replace "
            f"or remove: move {'them' if len(unowned) > 1 else 'it'} or write elsewhere (-o)"
        )


def _remove_written(entry: Path) -> None:
    """Remove ``entry`` (checked by check_output_folder: clflow wrote all of it)."""
    if entry.is_dir() and not entry.is_symlink():
        shutil.rmtree(entry)
    else:
        entry.unlink()


@contextlib.contextmanager
def atomic_dir(
    path: str | os.PathLike,
    replaces: tuple[str, ...] = (),
    inputs=(),
    *,
    derived: bool = False,
    source: str | os.PathLike | None = None,
) -> Iterator[Path]:
    """Yield a temporary folder next to folder ``path``; if the block succeeds, move what it
    holds into ``path`` (replacing entries of the same name), delete the entries of ``path``
    that match a glob pattern of ``replaces`` but were not written now (the earlier result's,
    e.g. its extra frames), with ``derived`` the folders derived from the earlier result, and record what
    was written in ``path``'s written-record (``source``: the folder this result derives from);
    else delete it. A failure leaves ``path`` as it was; a success leaves one result, never a
    mix. What clflow did not write, and ``inputs``, are never replaced or removed: refused
    on entering (call :func:`check_output_folder` before long work to refuse before it)."""
    path = Path(path)
    check_output_folder(path, replaces, inputs, derived=derived)
    path.parent.mkdir(parents=True, exist_ok=True)
    prefix = _temporary_prefix(path, path.name)
    tmp = Path(_creating(path, lambda: tempfile.mkdtemp(prefix=prefix, suffix=".tmp", dir=path.parent)))
    with _STAGING_LOCK:
        _STAGING.add(tmp.resolve())
    try:
        yield tmp
        written = sorted(entry.name for entry in tmp.iterdir())
        check_output_folder(path, tuple(glob.escape(name) for name in written), inputs)  # names outside ``replaces``
        for inner in tmp.rglob(WRITTEN_RECORD):  # its files' own records (atomic_path's): one for the whole
            inner.unlink()
        new_files = {
            file.relative_to(tmp).as_posix(): content_digest(file) for file in tmp.rglob("*") if not file.is_dir()
        }
        record = _written_record(path) if path.exists() else {"files": {}}
        if path.exists():
            stale = [old for pattern in replaces for old in path.glob(pattern) if old.name not in written]
            for old in {*stale, *(derived_folders(path) if derived else [])}:
                _remove_written(old)
            for name in written:
                target = path / name
                if target.is_dir() and not target.is_symlink():
                    shutil.rmtree(target)
        kept = {
            name: digest
            for name, digest in record["files"].items()
            if name.split("/")[0] not in written and (path / name).is_file()
        }
        record = {"files": {**kept, **new_files}}
        if source is not None:
            record["source"] = os.path.relpath(Path(source).resolve(), path.resolve())
        _write_record(tmp, record)
        with _signals_held():  # Ctrl-C or SIGTERM now would leave a mix: they land after the moves
            if not path.exists():
                tmp.chmod(0o777 & ~_umask())
                os.replace(tmp, path)
                return
            for entry in tmp.iterdir():
                os.replace(entry, path / entry.name)
    finally:
        with _STAGING_LOCK:
            _STAGING.discard(tmp.resolve())
        shutil.rmtree(tmp, ignore_errors=True)


#: the staging folders of this process's atomic_dir blocks: the files atomic_path writes
#: inside them skip their folder's written-record (one read and rewrite per file, O(n^2)
#: for n frames), since atomic_dir records the whole result when it moves it in
_STAGING: set[Path] = set()
_STAGING_LOCK = threading.Lock()


def _staged(folder: Path) -> bool:
    """Whether ``folder`` lies in a staging folder of an :func:`atomic_dir` of this process."""
    if not _STAGING:
        return False
    folder = folder.resolve()
    with _STAGING_LOCK:
        return any(stage == folder or stage in folder.parents for stage in _STAGING)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back until the block ends, then handled as they would have
    been (in the main thread, where Python handles signals; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    before = {sig: signal.signal(sig, lambda signum, frame: received.append(signum)) for sig in HELD_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
        for sig in received[:1]:
            handler = before[sig]
            if callable(handler):
                handler(sig, None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), sig)


def _write_record(folder: Path, record: dict) -> None:
    """``folder``'s written-record, replaced atomically (a reader sees the old or the new)."""
    import json

    fd, tmp = tempfile.mkstemp(prefix=f".record.{os.getpid()}.", suffix=".tmp", dir=folder)
    with os.fdopen(fd, "w") as fh:
        json.dump(record, fh, indent=1, sort_keys=True)
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, folder / WRITTEN_RECORD)


@contextlib.contextmanager
def _record_lock(folder: Path) -> Iterator[None]:
    """Hold ``folder``'s written-record for a read-modify-write (processes writing into one
    folder at once, e.g. parallel starts, each add their files)."""
    import fcntl

    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask
