"""Outputs are all or nothing, over nothing clflow did not write, one writer a folder: the
guarantees of clflow.fileio (docs/architecture.md, "Outputs"), each against the way it was
found broken: a stop inside the moves, two writers into one folder, a writer on another
host, a failed move, a file edited in place, temporaries' names that users' files share."""

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import clflow.fileio.writing as writing
from clflow.errors import InputError
from clflow.fileio import (
    LOCK_NAME,
    WRITTEN_RECORD,
    FolderBusy,
    atomic_dir,
    atomic_path,
    atomic_write_text,
    check_output_folder,
    folder_lock,
    output_folder,
    read_record,
)
from tests.fileio._writers import ENTRIES, held, recorded_exactly, result, write

ROOT = Path(__file__).resolve().parents[2]


def writers(*args, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "tests.fileio._writers", *map(str, args)],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT,
    )  # fmt: skip


def files_of(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# -- a stop at any moment ---------------------------------------------------------------------


def test_200_random_stops_leave_the_earlier_result_or_the_whole_new_one(tmp_path):
    """SIGKILL, SIGINT or SIGTERM at a random moment of each of 200 writes (their moves
    slowed, so many land inside them); after each, the next holder settles the folder: it
    holds the earlier result or the whole new one, recorded exactly, and no staging."""
    res = writers("kills", tmp_path / "out", 200, 57)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["bad"] == [], summary["bad"][:3]
    assert summary["unclean"] == [], (summary["unclean"][:3], res.stderr[-2000:])  # each stop ends the writer cleanly
    assert summary["earlier"] > 0 and summary["new"] > 0
    assert summary["stopped in the move"] >= 5, summary  # the test reaches the moves themselves


def test_a_move_that_fails_is_undone_and_the_next_write_owns_its_files(tmp_path, monkeypatch):
    """A record that cannot be replaced (an immutable file) fails the last step of a move:
    the earlier result and its record are put back, and the next write is not refused."""
    out = tmp_path / "out"
    write(out, 3)
    before = files_of(out)
    real = writing.write_record

    def immutable(folder, record, scratch):
        if folder == out:
            raise PermissionError(1, "Operation not permitted", str(folder / WRITTEN_RECORD))
        real(folder, record, scratch)

    monkeypatch.setattr(writing, "write_record", immutable)
    with pytest.raises(PermissionError, match="the earlier result is kept"):
        write(out, 4)
    assert files_of(out) == before and recorded_exactly(out)
    monkeypatch.setattr(writing, "write_record", real)
    write(out, 4)
    assert held(out) == result(4) and recorded_exactly(out)


_STOP_AT_REPLACE = """
import os, sys
import clflow.fileio.writing as writing
from clflow.fileio import atomic_write_text
def stop(src, dst):
    if os.path.basename(dst) == "params.json":
        os._exit(9)  # as kill -9 between the record and the move
    os.rename(src, dst)
writing.os.replace = stop
atomic_write_text(sys.argv[1], "new")
"""


def renames_stopped(monkeypatch, at: int, stop) -> tuple:
    """The writer's renames counted, ``stop()`` called before the ``at``-th; returns the real
    rename and the list of their destinations."""
    real, moves = os.rename, []

    def rename(src, dst):
        moves.append(dst)
        if len(moves) == at:
            stop()
        real(src, dst)

    monkeypatch.setattr(writing.os, "rename", rename)
    return real, moves


def test_an_exception_of_any_kind_inside_the_move_leaves_it_to_the_next_holder(tmp_path, monkeypatch):
    """Not an OSError (which is undone at once): the journal and the entries moved aside stay
    in the staging folder, and whoever holds the folder next finishes the move from them."""
    out = tmp_path / "out"
    write(out, 1)

    def fail():
        raise MemoryError

    real, moves = renames_stopped(monkeypatch, at=2, stop=fail)
    with pytest.raises(MemoryError):
        write(out, 2)
    monkeypatch.setattr(writing.os, "rename", real)
    assert [p.name for p in out.glob(".clflow-staging.*/journal.json")] == ["journal.json"]
    with output_folder(out):
        pass
    assert held(out) == result(2) and recorded_exactly(out)
    assert [p.name for p in out.iterdir() if p.name.startswith(".clflow-staging")] == []


def test_a_file_stopped_between_its_record_and_its_move_is_still_clflows(tmp_path):
    out = tmp_path / "out"
    atomic_write_text(out / "params.json", "old")
    res = subprocess.run([sys.executable, "-c", _STOP_AT_REPLACE, str(out / "params.json")], cwd=ROOT)
    assert res.returncode == 9 and (out / "params.json").read_text() == "old"
    check_output_folder(out, ("params.json",))  # either content is clflow's until the next write settles it
    atomic_write_text(out / "params.json", "newer")
    assert read_record(out).moving == {} and (out / "params.json").read_text() == "newer"
    assert [p.name for p in out.iterdir() if p.name.startswith(".clflow-staging")] == []


# -- writers at once --------------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 8])
def test_writers_at_once_are_refused_in_one_line_naming_the_holder(tmp_path, n):
    out = tmp_path / "out"
    res = writers("race", out, n, "refuse")
    lines = [json.loads(line) for line in res.stdout.splitlines()]
    written = [line["version"] for line in lines if line.get("written")]
    refused = [line["refused"] for line in lines if "refused" in line]
    assert len(lines) == n and written and len(written) + len(refused) == n
    assert all("is being written by another clflow run" in why and "--wait" in why for why in refused)
    assert any(f"`clflow race {out} {n} refuse`, pid" in why for why in refused) or not refused
    assert held(out) in [result(v) for v in written] and recorded_exactly(out)
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".clflow-")) == [WRITTEN_RECORD]


def test_writers_that_wait_write_one_after_another(tmp_path):
    out = tmp_path / "out"
    res = writers("race", out, 6, "wait")
    lines = [json.loads(line) for line in res.stdout.splitlines()]
    assert sorted(line["version"] for line in lines if line.get("written")) == [1, 2, 3, 4, 5, 6]
    assert held(out) in [result(v) for v in range(1, 7)] and recorded_exactly(out)


_HOLD = """
import signal, sys, time
from clflow.fileio import atomic_path, output_folder
{what}
"""
_HOLD_LOCK = _HOLD.format(what="with output_folder(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(60)")
_STALL_WRITE = _HOLD.format(
    what=textwrap.dedent(
        """
        with atomic_path(sys.argv[1] + "/theirs.txt") as tmp:
            tmp.write_text("theirs")
            print("staged", flush=True)
            sys.stdin.readline()  # until the test lets it go on
        print("written", flush=True)
        """
    )
)


def _start(script: str, *args, prefix=()) -> subprocess.Popen:
    proc = subprocess.Popen(
        [*prefix, sys.executable, "-c", script, *map(str, args)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    proc.stdout.readline()
    return proc


def test_a_lock_whose_holder_was_killed_is_taken_over_and_a_live_one_is_not(tmp_path):
    out = tmp_path / "out"
    proc = _start(_HOLD_LOCK, out)
    with pytest.raises(FolderBusy, match=r"out is being written by another clflow run \(`clflow .*`, pid \d+ on "):
        write(out, 1)
    proc.kill()
    proc.wait()
    assert (out / LOCK_NAME).exists()  # a killed holder's file stays; its lock went with it
    write(out, 1)
    assert held(out) == result(1) and not (out / LOCK_NAME).exists()
    with folder_lock(out), folder_lock(out):  # re-entrant within a process
        write(out, 2)
    assert held(out) == result(2)


def _wait_until_unlocked(claim: Path, seconds: float = 10.0) -> None:
    """Until no process holds ``claim``'s lock (its writer is gone)."""
    import fcntl
    import time

    deadline = time.monotonic() + seconds
    with open(claim, "r+") as fh:
        while True:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                assert time.monotonic() < deadline, f"{claim} still locked"
                time.sleep(0.01)


def _namespaces() -> list[tuple]:
    """Ways to run a writer as another machine would look: this namespace, and (where this
    machine lets us) its own PID namespace, whose process ids mean nothing here."""
    ways = [()]
    if shutil.which("unshare") and subprocess.run(["unshare", "-p", "-f", "true"], capture_output=True).returncode == 0:
        ways.append(("unshare", "-p", "-f", "--kill-child"))
    return ways


@pytest.mark.parametrize("prefix", _namespaces(), ids=lambda p: "pid-namespace" if p else "same-namespace")
def test_a_live_writer_elsewhere_keeps_its_staging_and_a_dead_ones_goes(tmp_path, monkeypatch, prefix):
    """A writer whose process id means nothing here (another PID namespace, another host):
    writes beside it, into the same folder and its parent, leave its staging alone (its
    claim is locked), it then finishes; one killed mid-write is removed by the next write."""
    import socket

    monkeypatch.setattr(socket, "gethostname", lambda: "another-host")
    out = tmp_path / "shared" / "out"
    out.mkdir(parents=True)
    proc = _start(_STALL_WRITE, out, prefix=prefix)
    staging = [p for p in out.iterdir() if p.name.startswith(".clflow-staging")]
    assert len(staging) == 1
    atomic_write_text(out / "ours.txt", "ours")
    write(out, 1)
    write(tmp_path / "shared" / "sibling", 1)
    assert staging[0].is_dir()
    proc.stdin.write("\n")
    proc.stdin.flush()
    assert proc.stdout.readline().strip() == "written" and proc.wait() == 0
    assert (out / "theirs.txt").read_text() == "theirs"
    check_output_folder(out, ("theirs.txt", "ours.txt", *ENTRIES))  # all recorded as clflow's

    proc = _start(_STALL_WRITE, out, prefix=prefix)
    proc.kill()
    proc.wait()
    _wait_until_unlocked(next(out.glob(".clflow-staging.*/claim.json")))  # a namespace's child dies after unshare
    atomic_write_text(out / "ours.txt", "again")
    assert not [p for p in out.iterdir() if p.name.startswith(".clflow-staging")]
    assert (out / "theirs.txt").read_text() == "theirs"


# -- what is the user's -----------------------------------------------------------------------


def _users_temporaries(folder: Path) -> dict[str, bytes]:
    """Files and folders whose names look like any tool's temporaries, some with pids no process has."""
    (folder / ".photos.2023.summer.tmp").mkdir(parents=True)
    (folder / ".photos.2023.summer.tmp" / "img1.jpg").write_bytes(b"jpeg")
    (folder / ".notes.99999.v2.tmp.txt").write_text("notes")
    (folder / ".draft.31337.final.tmp").write_text("draft")
    (folder / ".out.4000000.abcdef.tmp").mkdir()
    (folder / ".out.4000000.abcdef.tmp" / "mine").write_text("mine")
    (folder / ".clflow-staging.0123456789abcdef0123456789abcdef").mkdir()  # our pattern, no claim
    (folder / ".clflow-staging.0123456789abcdef0123456789abcdef" / "data").write_text("theirs")
    return files_of(folder)


def test_files_named_like_temporaries_beside_and_inside_the_output_stay(tmp_path):
    beside = _users_temporaries(tmp_path)
    inside = _users_temporaries(tmp_path / "out")
    for version in (1, 2):
        write(tmp_path / "out", version)
        atomic_write_text(tmp_path / "out" / "params.json", str(version))
        atomic_write_text(tmp_path / "note.json", str(version))
    assert {n: d for n, d in files_of(tmp_path).items() if n in beside} == beside
    assert {n: d for n, d in files_of(tmp_path / "out").items() if n in inside} == inside


def test_a_staging_folder_is_removed_only_when_its_claim_proves_it_clflows(tmp_path):
    out = tmp_path / "out"
    write(out, 1)
    forged = out / ".clflow-staging.00000000000000000000000000000000"
    forged.mkdir()
    (forged / "claim.json").write_text(json.dumps({"token": "ffffffffffffffffffffffffffffffff"}))
    (forged / "data").write_text("a user's")
    empty = out / ".clflow-staging.11111111111111111111111111111111"
    empty.mkdir()
    with output_folder(out):
        pass
    assert (forged / "data").read_text() == "a user's" and not empty.exists()


def test_links_and_empty_folders_are_the_users_by_one_rule(tmp_path):
    """A link to a folder, a link to a file and an empty folder put into a result clflow
    wrote: each is refused in one line, none removed."""
    out = tmp_path / "out"
    write(out, 1)
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "precious").write_text("p")
    for name, make in {
        "to_folder": lambda p: p.symlink_to(tmp_path / "elsewhere"),
        "to_file": lambda p: p.symlink_to(tmp_path / "elsewhere" / "precious"),
        "empty": lambda p: p.mkdir(),
    }.items():
        make(out / "sub" / name)
        with pytest.raises(InputError, match=rf"out holds sub/{name}/?, which clflow did not write"):
            write(out, 2)
        assert os.path.lexists(out / "sub" / name) and (tmp_path / "elsewhere" / "precious").exists()
        (out / "sub" / name).rmdir() if name == "empty" else (out / "sub" / name).unlink()
    write(out, 2)
    assert held(out) == result(2)


def test_a_large_file_edited_in_place_is_refused_and_an_unchanged_one_is_not_read(tmp_path, monkeypatch):
    out = tmp_path / "out"
    with atomic_path(out / "positions.npz") as tmp:
        with open(tmp, "wb") as fh:
            fh.truncate(72 * 2**20)  # 72 MB, past any size-only shortcut
    import clflow.fileio.record as record

    monkeypatch.setattr(record, "content_digest", lambda path: pytest.fail(f"read {path}"))
    check_output_folder(out, ("positions.npz",))  # its fingerprint says it is as written
    monkeypatch.undo()
    with open(out / "positions.npz", "r+b") as fh:  # the same size, other bytes
        fh.seek(50 * 2**20)
        fh.write(b"edited")
    with pytest.raises(InputError, match=r"out holds positions.npz, which clflow did not write \(or which changed"):
        check_output_folder(out, ("positions.npz",))


def test_a_damaged_or_missing_record_is_named_with_the_way_out(tmp_path):
    out = tmp_path / "out"
    write(out, 1)
    (out / WRITTEN_RECORD).write_text("{not json")
    with pytest.raises(InputError, match=r"its record of the files clflow wrote \(\.clflow-written\.json\) is damaged "
                                         r"\(unreadable: JSONDecodeError\), so clflow cannot tell .* move what you"):  # fmt: skip
        write(out, 2)
    (out / WRITTEN_RECORD).unlink()
    with pytest.raises(InputError, match=r"which clflow did not write \(the folder has no \.clflow-written\.json"):
        write(out, 2)
    assert held(out) == result(1)


def test_a_stop_while_a_folder_is_first_made_leaves_no_folder(tmp_path):
    out = tmp_path / "new"
    with pytest.raises(KeyboardInterrupt):
        with atomic_dir(out, ENTRIES) as new:
            (new / "frame_0.txt").write_text("x")
            raise KeyboardInterrupt
    assert not out.exists()


def test_a_link_to_nothing_is_refused_before_the_work(tmp_path):
    (tmp_path / "DL").symlink_to(tmp_path / "gone")
    with pytest.raises(InputError, match=r"DL is a symbolic link to .*gone, which does not exist"):
        with output_folder(tmp_path / "DL"):
            pytest.fail("entered")


@pytest.mark.parametrize(
    "stop", [signal.SIGTERM, signal.SIGALRM], ids=["TERM", "ALRM"]
)  # a scheduler's, a time limit's
def test_a_stop_inside_the_move_lands_after_it(tmp_path, monkeypatch, stop):
    out = tmp_path / "out"
    write(out, 1)

    def terminate(signum, frame):
        raise KeyboardInterrupt

    before = signal.signal(stop, terminate)
    _, moves = renames_stopped(monkeypatch, at=2, stop=lambda: os.kill(os.getpid(), stop))
    try:
        with pytest.raises(KeyboardInterrupt):
            write(out, 2)
    finally:
        signal.signal(stop, before)
    assert len(moves) > 2 and held(out) == result(2) and recorded_exactly(out)


def test_a_stop_while_the_result_is_hashed_lands_after_the_hashing_threads(tmp_path, monkeypatch):
    """A Ctrl-C raised inside concurrent.futures' bookkeeping breaks it (RuntimeError:
    release unlocked lock; or a worker left on a lock, hanging the exit): it is handled once
    the threads are done, as a KeyboardInterrupt, the earlier result kept."""
    out = tmp_path / "out"
    write(out, 1)
    real, hashed, handled_after = writing.content_digest, [], []

    def slow_digest(path):
        if not hashed:
            os.kill(os.getpid(), signal.SIGINT)  # from a hashing thread, the first file begun
        time.sleep(0.01)
        hashed.append(path)
        return real(path)

    def interrupt(signum, frame):
        handled_after.append(len(hashed))
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGINT, interrupt)
    monkeypatch.setattr(writing, "content_digest", slow_digest)
    try:
        with pytest.raises(KeyboardInterrupt):
            with atomic_dir(out, replaces=ENTRIES) as new:
                for k in range(24):
                    (new / f"frame_{k}.txt").write_text(f"frame {k}\n")
    finally:
        signal.signal(signal.SIGINT, before)
    assert handled_after == [24] and held(out) == result(1) and recorded_exactly(out)
