"""Writing outputs: all or nothing, over nothing clflow did not write, one writer a folder.

    with output_folder("out"):                   # locked for this run; a dead run's leftovers finished
        check_output_folder("out", ENTRIES)      # refuse before the work
        ...
        with atomic_dir("out", ENTRIES) as new:  # stage the whole result
            ...                                  # write into new/
        # now out holds the whole new result, or (on an exception) the earlier one
    with atomic_path("out/params.json") as tmp:  # one file, the same way
        tmp.write_text(text)

Every temporary lives in a staging folder ``.clflow-staging.<token>`` inside the folder it
is for, never beside it. The staging folder holds ``claim.json`` with the token its name
has, flock(2)-ed by its writer while it lives: a staging folder is clflow's when its claim
names its token, and its writer is gone when its claim can be locked (whatever machine or
process namespace the writer ran in). Only those are ever removed.

A result moves in as a journaled transaction (:class:`_Transaction`): the journal in the
staging folder lists the earlier entries to move aside and the new ones to move in; from
its being written (synced) the move is committed, and whoever holds the folder next
(:func:`output_folder`) finishes it from the journal, or, where the writer itself failed
mid-move and wrote that it was undoing it, undoes it. So at any instant the folder plus
its journal is the earlier result or the whole new one, kill -9 and power loss included.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import os
import re
import secrets
import shutil
import signal
import threading
from pathlib import Path
from typing import Iterator

from clflow.errors import InputError
from clflow.fileio import record
from clflow.fileio.digest import content_digest, fingerprint
from clflow.fileio.lock import folder_lock
from clflow.fileio.record import (
    FOLDER,
    WRITTEN_RECORD,
    Record,
    is_bookkeeping,
    read_record,
    targets,
    unowned_files,
    write_record,
)

#: the signals a result's last moves hold back (Ctrl-C, what schedulers send, and the alarm
#: of a sweep's time limit: each handler raises, and an exception inside the moves would
#: leave them half made)
HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)
STAGING = re.compile(r"\.clflow-staging\.(?P<token>[0-9a-f]{32})")
CLAIM, JOURNAL = "claim.json", "journal.json"


@contextlib.contextmanager
def output_folder(path: str | os.PathLike, *, shared: bool = False) -> Iterator[Path]:
    """Hold folder ``path`` while the block runs: made if missing, locked against other
    clflow runs (clflow.fileio.lock; ``shared``: a reader's hold), an interrupted write there
    finished or undone and dead writers' staging folders removed. A folder this call made
    is removed again if it is left empty."""
    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise InputError(
            f"{path} is a symbolic link to {os.readlink(path)}, which does not exist: make it, or write elsewhere (-o)"
        )
    if path.exists() and not path.is_dir():
        raise InputError(f"output folder {path} is a file, not a folder")
    made = not path.exists()
    if made:
        path.mkdir(parents=True, exist_ok=True)
    try:
        if shared and any(STAGING.fullmatch(entry) for entry in os.listdir(path)):
            with folder_lock(path), contextlib.suppress(OSError):  # a reader first settles a dead writer's move
                _settle(path)
        with folder_lock(path, shared=shared) as first:
            if first and not shared:
                _settle(path)
            yield path
    finally:
        if made:
            with contextlib.suppress(OSError):
                path.rmdir()


def check_output_folder(path: str | os.PathLike, entries: tuple[str, ...], inputs=(), *, derived: bool = False) -> None:
    """clflow.fileio.record.check_output_folder, once the folders among what it would replace
    are settled (a dead writer's move there finished or undone; refused while a live one
    writes there): their staging folders are clflow's to remove then, and another's not."""
    path = Path(path)
    if path.is_dir():
        for target in record.targets(path, entries, derived=derived):
            for root, dirs, _ in os.walk(target) if target.is_dir() and not target.is_symlink() else ():
                if any(STAGING.fullmatch(d) for d in dirs):
                    with output_folder(root):
                        pass
                dirs[:] = [d for d in dirs if not is_bookkeeping(d)]
    record.check_output_folder(path, entries, inputs, derived=derived)


def check_output_file(path: str | os.PathLike) -> None:
    """Refuse (InputError, one line) a write of file ``path`` over one clflow did not write."""
    path = Path(path)
    check_output_folder(path.parent, (glob.escape(path.name),))


def _settle(folder: Path) -> None:
    """Finish (or undo) the moves of dead writers' transactions in ``folder`` and remove
    their staging folders (the caller holds the folder's lock)."""
    for name in sorted(os.listdir(folder)):
        match = STAGING.fullmatch(name)
        stage = folder / name
        if match is None or stage.is_symlink() or not stage.is_dir():
            continue
        with _dead_claim(stage, match["token"]) as dead:
            if dead:
                journal = _read_journal(stage)
                if journal is not None:
                    _Transaction(folder, stage, journal).finish(verify=True)
                shutil.rmtree(stage, ignore_errors=True)


@contextlib.contextmanager
def _dead_claim(stage: Path, token: str) -> Iterator[bool]:
    """Whether staging folder ``stage`` is clflow's and its writer gone, held so through the
    block: its claim names its token and can be locked; or, stopped before its claim was in
    place, it holds nothing but that claim's temporary, which can be locked, or nothing."""
    import fcntl

    claim = stage / CLAIM
    if not claim.exists():
        left = os.listdir(stage)
        if not left:
            yield True
            return
        if left != [CLAIM + ".tmp"]:
            yield False  # not a claim of clflow's making: nobody's to remove
            return
        claim = stage / left[0]
    try:
        fd = os.open(claim, os.O_RDWR | os.O_CLOEXEC)
    except OSError:
        yield False
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # alive (held), or no locks on this file system: unknown
            yield False
            return
        if claim.name != CLAIM:
            yield True
            return
        try:
            yield json.loads(os.pread(fd, 4096, 0)).get("token") == token
        except (OSError, ValueError, AttributeError):
            yield False
    finally:
        os.close(fd)


class _Claim:
    """A staging folder ``.clflow-staging.<token>`` in ``folder``, claimed (locked) for this
    writer's life and removed with all it holds when it ends. The claim is written and
    locked under a temporary name and then renamed into place, so a claim.json is always
    whole and held; a staging folder that another run's settling removed while it was being
    claimed is made again."""

    def __init__(self, folder: Path):
        for _ in range(10):
            self.token = secrets.token_hex(16)
            self.path = folder / f".clflow-staging.{self.token}"
            try:
                self.path.mkdir()
            except OSError as exc:
                raise OSError(
                    exc.errno, f"cannot write here ({(exc.strerror or str(exc)).lower()})", str(folder)
                ) from None
            with contextlib.suppress(FileNotFoundError, BlockingIOError):  # settled away meanwhile: again
                self.fd = self._claim()
                break
        else:
            raise OSError(errno.EAGAIN, "cannot claim a staging folder here", str(folder))
        with _STAGING_LOCK:
            _STAGING.add(self.path.resolve())

    def _claim(self) -> int:
        import fcntl

        tmp = self.path / (CLAIM + ".tmp")
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise  # a settling run holds it and will remove the folder: claim another
            except OSError:
                pass  # no locks on this file system: never judged dead
            os.pwrite(fd, json.dumps({"token": self.token, "pid": os.getpid()}).encode(), 0)
            os.rename(tmp, self.path / CLAIM)
        except BaseException:
            os.close(fd)
            raise
        return fd

    def close(self) -> None:
        """Let go of the claim and remove the staging folder, unless it holds a journal: a
        move (or its undo) begun and not ended, by an exception of any kind, which the
        folder's next holder finishes from it (its claim, no longer locked, is dead)."""
        with _STAGING_LOCK:
            _STAGING.discard(self.path.resolve())
        if not (self.path / JOURNAL).exists():
            shutil.rmtree(self.path, ignore_errors=True)
        os.close(self.fd)


#: the staging folders of this process: what atomic_path writes inside one is part of that
#: result (recorded, and made atomic, with it), so it is written in place
_STAGING: set[Path] = set()
_STAGING_LOCK = threading.Lock()


def _staged(folder: Path) -> bool:
    """Whether ``folder`` lies in a staging folder of this process."""
    if not _STAGING:
        return False
    folder = folder.resolve()
    with _STAGING_LOCK:
        return any(stage in folder.parents or stage == folder for stage in _STAGING)


class _Transaction:
    """The move of a staged result into ``folder`` (see the module's docstring): the earlier
    entries ``old`` go aside into ``stage/old``, the new ``new`` come in from ``stage/new``,
    then the record. Each step can be taken again: a step found done is skipped."""

    def __init__(self, folder: Path, stage: Path, journal: dict):
        self.folder, self.stage, self.journal = folder, stage, journal
        self.old, self.new = journal["old"], journal["new"]

    def commit(self) -> None:
        """Journal the move (the commit point), then make it; a move that fails is undone."""
        _write_synced(self.stage / JOURNAL, self.journal)
        _sync(self.stage)
        try:
            self.finish()
        except OSError as exc:
            self.journal["undo"] = True
            try:
                _write_synced(self.stage / JOURNAL, self.journal)
                self.undo()
            except OSError:
                raise OSError(
                    exc.errno,
                    f"{(exc.strerror or str(exc)).lower()}; the move of the new result stopped half-way and could "
                    f"not be undone: clflow's next write to {self.folder} finishes it",
                    exc.filename,
                ) from None
            raise OSError(
                exc.errno, f"{(exc.strerror or str(exc)).lower()}; the earlier result is kept", exc.filename
            ) from None

    def finish(self, verify: bool = False) -> None:
        """Make the journaled move (or, if the journal says so, undo it); ``verify``: a dead
        writer's, whose new files are fingerprinted only where they still hold what it wrote."""
        if self.journal.get("undo"):
            self.undo()
            return
        aside = self.stage / "old"
        aside.mkdir(exist_ok=True)
        for name in self.old:
            here, new = self.folder / name, self.stage / "new" / name
            if (
                not os.path.lexists(aside / name)
                and os.path.lexists(here)
                and (name not in self.new or os.path.lexists(new))
            ):
                os.rename(here, aside / name)
        for name in self.new:
            if os.path.lexists(self.stage / "new" / name):
                if os.path.lexists(self.folder / name):
                    raise FileExistsError(errno.EEXIST, "appeared while the result moved in", str(self.folder / name))
                os.rename(self.stage / "new" / name, self.folder / name)
        record = Record(**self.journal["record"])
        for name, digest in record.files.items():  # the new files' fingerprints, as they lie now
            if name.split("/")[0] in self.new and digest != FOLDER:
                here = self.folder / name
                if not verify or (here.is_file() and content_digest(here) == digest):
                    record.stats[name] = fingerprint(here)
        write_record(self.folder, record, self.stage)
        _sync(self.folder)
        (self.stage / JOURNAL).unlink()

    def undo(self) -> None:
        """Put the earlier result back (each new entry out, each earlier one in) and its record."""
        staged, aside = self.stage / "new", self.stage / "old"
        for name in self.new:
            here = self.folder / name
            moved_in = not os.path.lexists(staged / name) and os.path.lexists(here)
            if moved_in and (name not in self.old or os.path.lexists(aside / name)):
                os.rename(here, staged / name)
        for name in self.old:
            if os.path.lexists(aside / name):
                os.rename(aside / name, self.folder / name)
        earlier = self.journal.get("earlier_record")
        if earlier is not None and read_record(self.folder).to_json() != earlier:  # replaced before the stop
            write_record(self.folder, Record(**earlier), self.stage)
        _sync(self.folder)
        (self.stage / JOURNAL).unlink()


def _read_journal(stage: Path) -> dict | None:
    try:
        journal = json.loads((stage / JOURNAL).read_text())
    except (OSError, ValueError):
        return None  # none (not committed: the folder was not touched) or not yet synced
    return journal if isinstance(journal, dict) and {"old", "new", "record"} <= journal.keys() else None


def _write_synced(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(data, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _sync(path: Path) -> None:
    """fsync ``path``: a file's data, or a folder's entries (not what they hold)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | (os.O_DIRECTORY if path.is_dir() else 0))
    except OSError:
        return  # a link: nothing of its own to sync
    try:
        os.fsync(fd)
    except OSError:
        pass  # file systems that cannot sync (some FUSE, /proc)
    finally:
        os.close(fd)


def _sync_tree(folder: Path) -> None:
    """fsync every file and folder under ``folder`` (a staged result, before its journal), at
    once from threads: the file system commits concurrent syncs together, where one at a
    time each costs a commit of its own."""
    paths = [Path(root, name) for root, dirs, files in os.walk(folder) for name in files + dirs]
    _in_threads(_sync, paths, workers=32)
    _sync(folder)


def _in_threads(fn, items: list, workers: int) -> list:
    """``[fn(item) for item in items]`` from up to ``workers`` threads, with HELD_SIGNALS
    held back until they are done: an exception raised inside concurrent.futures'
    bookkeeping in this thread (a semaphore's or a future's condition) breaks it (RuntimeError:
    release unlocked lock, or a worker left waiting on a lock no one releases, which hangs the
    interpreter's exit), where a stop handled after it is an ordinary KeyboardInterrupt."""
    from concurrent.futures import ThreadPoolExecutor

    with _signals_held(), ThreadPoolExecutor(max_workers=max(1, min(workers, len(items)))) as pool:
        return list(pool.map(fn, items))


@contextlib.contextmanager
def atomic_dir(
    path: str | os.PathLike,
    replaces: tuple[str, ...] = (),
    inputs=(),
    *,
    derived: bool = False,
    source: str | os.PathLike | None = None,
) -> Iterator[Path]:
    """Yield a staging folder for a result in folder ``path``; if the block succeeds, move
    what it holds into ``path`` as one step (replacing entries of the same name), together
    with removing the entries of ``path`` that match a glob pattern of ``replaces`` but were
    not written now (the earlier result's, e.g. its extra frames) and, with ``derived``, the
    folders derived from the earlier result; ``source``: the folder this result derives from,
    recorded. A failure leaves ``path`` as it was. What clflow did not write, and
    ``inputs``, are never replaced or removed: refused on entering and again before the move
    (call :func:`check_output_folder` before long work to refuse before it)."""
    path = Path(path)
    with output_folder(path):
        check_output_folder(path, replaces, inputs, derived=derived)
        claim = _Claim(path)
        try:
            new = claim.path / "new"
            new.mkdir()
            yield new
            written = sorted(os.listdir(new))
            escaped = tuple(glob.escape(name) for name in written)
            check_output_folder(path, (*replaces, *escaped), inputs, derived=derived)  # as the folder is now
            earlier = read_record(path)
            old = sorted({e.name for e in targets(path, (*replaces, *escaped), derived=derived)})
            files = {**_recorded(earlier, path, {*old, *written}), **_digests(new)}
            kept = {n: earlier.stats[n] for n in files if n in earlier.stats and n.split("/")[0] not in written}
            record = Record(files=files, stats=kept)
            if source is not None:
                record.source = os.path.relpath(Path(source).resolve(), path.resolve())
            _sync_tree(new)
            journal = {
                "old": old,
                "new": written,
                "record": {"files": record.files, "stats": record.stats, "source": record.source},
                "earlier_record": None if earlier.problem else earlier.to_json(),
            }
            with _signals_held():  # Ctrl-C, SIGTERM or a time limit now lands after the move, not inside it
                _Transaction(path, claim.path, journal).commit()
        finally:
            claim.close()


def _recorded(record: Record, folder: Path, replaced: set[str]) -> dict[str, str]:
    """``record``'s files that stay: not under a replaced entry, and still there."""
    return {
        name: digest
        for name, digest in record.files.items()
        if name.split("/")[0] not in replaced and os.path.lexists(folder / name.rstrip("/"))
    }


def _digests(new: Path) -> dict[str, str]:
    """The record's files of staged result ``new``: each file's digest (hashed from threads:
    SHA-256 lets go of the GIL, so each core hashes a file), each empty folder."""
    files, folders = {}, {}
    for root, dirs, names in os.walk(new):
        rel = Path(root).relative_to(new).as_posix()
        for name in names:
            files[f"{name}" if rel == "." else f"{rel}/{name}"] = Path(root, name)
        if not dirs and not names and rel != ".":
            folders[f"{rel}/"] = FOLDER
    digests = dict(zip(files, _in_threads(content_digest, list(files.values()), workers=os.cpu_count() or 1)))
    return {**digests, **folders}


def remove_entries(path: str | os.PathLike, entries: tuple[str, ...]) -> list[str]:
    """Remove the entries of folder ``path`` that glob patterns ``entries`` match, as one
    step (refused, InputError, if clflow did not write all of them); returns their names."""
    path = Path(path)
    if not path.is_dir():
        return []
    gone = [e.name for e in targets(path, entries)]
    if gone:
        with atomic_dir(path, replaces=entries):
            pass
    return gone


def discard_written(path: str | os.PathLike) -> None:
    """Remove, as one step, what clflow wrote in folder ``path`` (a first run's, on its
    failure) and the folder if nothing else is left in it; the rest stays."""
    path = Path(path)
    if not path.is_dir():
        return
    ours = [e for e in path.iterdir() if not is_bookkeeping(e.name) and not unowned_files(path, e)]
    remove_entries(path, tuple(glob.escape(e.name) for e in ours))
    if all(is_bookkeeping(name) for name in os.listdir(path)):  # the lock goes with its holder
        (path / WRITTEN_RECORD).unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            path.rmdir()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path for file ``path`` (its suffix kept, so writers that choose a
    format by the extension behave); if the block succeeds, move it onto ``path`` and list
    it in the folder's record; else nothing is left. Refuses (InputError) to replace a file
    clflow did not write. Inside a staging folder of :func:`atomic_dir` the file is written in
    place: the result it belongs to is moved and recorded as a whole."""
    path = Path(path)
    if _staged(path.parent):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()
        try:
            yield path
        except BaseException:
            path.unlink(missing_ok=True)
            raise
        return
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    name = (glob.escape(path.name),)
    check_output_folder(folder, name)
    claim = _Claim(folder)
    try:
        tmp = claim.path / path.name
        tmp.touch()
        yield tmp
        digest = content_digest(tmp)
        _sync(tmp)
        with output_folder(folder), _signals_held():
            check_output_folder(folder, name)  # as the folder is now
            record = _settled(folder, read_record(folder))
            record.moving[path.name] = digest  # stopped mid-move: either content is clflow's
            write_record(folder, record, claim.path)
            os.replace(tmp, path)
            del record.moving[path.name]
            record.files[path.name], record.stats[path.name] = digest, fingerprint(path)
            write_record(folder, record, claim.path)
    finally:
        claim.close()


def _settled(folder: Path, record: Record) -> Record:
    """``record`` with the files that writers stopped moving in settled: kept as clflow's
    where the file holds the moved content, dropped where it holds neither."""
    for name, digest in list(record.moving.items()):
        if (folder / name).is_file() and content_digest(folder / name) == digest:
            record.files[name] = digest
            record.stats.pop(name, None)
        del record.moving[name]
    return record


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def copy_file(source: str | os.PathLike, path: str | os.PathLike) -> None:
    """Copy file ``source`` to ``path`` as :func:`atomic_path` writes it."""
    with atomic_path(path) as tmp:
        shutil.copyfile(source, tmp)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """HELD_SIGNALS held back until the block ends, then the first handled as it would have
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


__all__ = [
    "HELD_SIGNALS",
    "atomic_dir",
    "atomic_path",
    "atomic_write_text",
    "check_output_file",
    "check_output_folder",
    "copy_file",
    "discard_written",
    "output_folder",
    "remove_entries",
]
