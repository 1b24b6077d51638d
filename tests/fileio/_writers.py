"""Writers that tests kill or race, run as ``python -m tests.fileio._writers MODE ...`` in a
process of their own that imports clflow.fileio alone (so forking it is safe).

Each result is made by :func:`result`: version v is ``v % 5 + 1`` frames ``frame_k.txt``
plus ``sub/a.txt``, each file's text naming v, so a folder is one whole version or it is
not, and stale frames of a longer earlier version must go.

- ``kills FOLDER N SEED``: N times, fork a writer of the next version into FOLDER (its
  moves slowed, so a stop lands inside them too), stop it at a random moment with SIGKILL,
  SIGINT or SIGTERM, then settle the folder as the next run does and check it holds the
  earlier committed version or the new one, whole, and a record that lists exactly it,
  and that the writer ended as a stop ends it (interrupted or killed; one that failed
  otherwise or hung is listed as unclean). Prints a JSON summary.
- ``race FOLDER N WAIT``: fork N writers that start together; each prints a JSON line.
"""

from __future__ import annotations

import json
import os
import random
import signal
import sys
import time
from pathlib import Path

import clflow.fileio.writing as writing
from clflow.fileio import FolderBusy, atomic_dir, content_digest, output_folder, read_record, wait_for_writers

ENTRIES = ("frame_*.txt", "sub")
STOPS = {signal.SIGINT, signal.SIGTERM}


def result(version: int) -> dict[str, str]:
    """Version ``version``'s files: relative path -> text."""
    files = {f"frame_{k}.txt": f"version {version} frame {k}\n" for k in range(version % 5 + 1)}
    files["sub/a.txt"] = f"version {version} sub\n"
    return files


def write(folder: Path, version: int) -> None:
    with atomic_dir(folder, replaces=ENTRIES) as new:
        for name, text in result(version).items():
            (new / name).parent.mkdir(parents=True, exist_ok=True)
            (new / name).write_text(text)


def held(folder: Path) -> dict[str, str]:
    """The folder's files but clflow's bookkeeping, and their text."""
    return {
        p.relative_to(folder).as_posix(): p.read_text()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not any(part.startswith(".clflow-") for part in p.relative_to(folder).parts)
    }


def recorded_exactly(folder: Path) -> bool:
    """Whether the record lists each file the folder holds with its content, and nothing else."""
    record = read_record(folder)
    files = held(folder)
    return set(record.files) == set(files) and all(record.files[n] == content_digest(folder / n) for n in files)


def slowed_renames() -> None:
    """Each rename in the writer takes a little longer, so stops land inside the moves."""
    rename = os.rename

    def slow(src, dst):
        time.sleep(0.005)
        rename(src, dst)

    writing.os.rename = slow


def as_a_command() -> None:
    """The signal handling of a clflow command: SIGINT and SIGTERM raise KeyboardInterrupt."""

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)


def kills(folder: Path, n: int, seed: int) -> dict:
    rng = random.Random(seed)
    slowed_renames()
    write(folder, 0)
    began = time.perf_counter()
    write(folder, 0)
    whole = time.perf_counter() - began  # a stop anywhere from before the staging to after the move
    committed, outcomes, mixed, unclean = 0, {"earlier": 0, "new": 0, "stopped in the move": 0}, [], []
    for version in range(1, n + 1):
        signal.pthread_sigmask(signal.SIG_BLOCK, STOPS)  # until the child has a command's handlers
        pid = os.fork()
        if pid == 0:
            as_a_command()
            try:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)
                write(folder, version)
            except KeyboardInterrupt:
                os._exit(130)
            except BaseException as exc:  # a stop that broke something else: said, and failed
                os.write(2, f"version {version}: {exc!r}\n".encode())
                os._exit(1)
            os._exit(0)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOPS)
        time.sleep(rng.uniform(0, 1.2 * whole))
        stop = rng.choice([signal.SIGKILL, signal.SIGKILL, signal.SIGINT, signal.SIGTERM])
        os.kill(pid, stop)
        status = exited(pid, within=30.0)
        if status not in (0, 130, -signal.SIGKILL):  # a write ends, is interrupted, or is killed
            unclean.append({"version": version, "stop": stop.name, "status": status})
        journals = list(folder.glob(".clflow-staging.*/journal.json"))
        outcomes["stopped in the move"] += bool(journals)
        with output_folder(folder):  # the next run: finishes or undoes what the stopped one left
            pass
        files = held(folder)
        if files == result(version):
            committed, outcomes["new"] = version, outcomes["new"] + 1
        elif files == result(committed):
            outcomes["earlier"] += 1
        else:
            mixed.append({"version": version, "files": files})
        if not recorded_exactly(folder) or any(p.name.startswith(".clflow-staging") for p in folder.iterdir()):
            mixed.append({"version": version, "unrecorded or left staged": sorted(os.listdir(folder))})
    return {"kills": n, **outcomes, "bad": mixed, "unclean": unclean, "write_s": whole}


def exited(pid: int, within: float) -> int | str:
    """Child ``pid``'s exit status (its code, or minus the signal that ended it); one that
    has not ended ``within`` seconds is killed and reported as ``"hung"``."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        time.sleep(0.01)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    return "hung"


def race(folder: Path, n: int, wait: bool) -> None:
    wait_for_writers(wait)
    start = time.time() + 0.5
    children = []
    for version in range(1, n + 1):
        pid = os.fork()
        if pid == 0:
            time.sleep(max(0.0, start - time.time()))
            try:
                write(folder, version)
                line = {"version": version, "written": True}
            except FolderBusy as exc:
                line = {"version": version, "refused": str(exc)}
            os.write(1, (json.dumps(line) + "\n").encode())  # one write: lines of writers at once stay whole
            os._exit(0)
        children.append(pid)
    for pid in children:
        os.waitpid(pid, 0)


if __name__ == "__main__":
    mode, folder = sys.argv[1], Path(sys.argv[2])
    if mode == "kills":
        print(json.dumps(kills(folder, int(sys.argv[3]), int(sys.argv[4]))))
    else:
        race(folder, int(sys.argv[3]), sys.argv[4] == "wait")
