"""The written-record: a command replaces or removes only what clflow wrote (each output folder's
written-record, clflow.fileio.WRITTEN_RECORD, lists it with its content), never an input of
the same run, and refuses in one line before any work when it would. Driven through the CLI
as a user would; the user's files are hashed before and after."""

import hashlib
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from clflow.fileio import WRITTEN_RECORD, atomic_dir, atomic_write_text, check_output_folder
from clflow.pipeline.runs import RESULTS
from tests.pipeline.test_refusals import one_error, run

SIMULATE = ("--set", "simulation.frames=1", "--preview", "none")


def digests(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (its relative path) and the SHA-256 of its bytes."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def leftovers_name(name: str) -> bool:
    """Whether relative path ``name`` is a temporary of clflow's: in a staging folder, or a
    lock that a killed run left (the next writer there takes it over)."""
    return ".clflow-staging." in name or name.endswith(".clflow-lock")


def leftovers(folder: Path) -> list[Path]:
    """clflow's temporaries under ``folder``."""
    return [p for p in folder.rglob(".clflow-*") if leftovers_name(p.as_posix())]


def user_folder(folder: Path, files: dict[str, str]) -> dict[str, str]:
    for name, text in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)
    return digests(folder)


def test_simulate_refuses_to_write_over_its_own_guidance_video(quick_demo, tmp_path):
    """`cp -r demo S; clflow simulate S/config.yaml -o S`: the preview would replace the
    config's guidance frames (S/guidance/), and without one the run would remove them as
    an earlier preview; into S/sim it writes."""
    copy = tmp_path / "S"
    shutil.copytree(quick_demo, copy)
    before = digests(copy)
    for preview in ("mp4", "none"):
        res = run("simulate", copy / "config.yaml", "--set", "simulation.frames=1", "--preview", preview, "-o", copy)
        one_error(res, r"S/guidance is an input of this run and one of its outputs: write elsewhere \(-o\)")
        assert "simulating" not in res.stderr and digests(copy) == before
    res = run("simulate", copy / "config.yaml", *SIMULATE, "-o", copy / "sim")
    assert res.returncode == 0, res.stderr
    after = digests(copy)
    assert {name: after[name] for name in before} == before and "sim/frame_001.ply" in after


def test_simulate_leaves_a_users_frames_and_folders_and_says_so_before_the_work(quick_demo, tmp_path):
    folder = tmp_path / "mine"
    before = user_folder(
        folder,
        {"notes.txt": "n", "frame_999.ply": "a", "frame_2.ply": "b", "render4d/mine.txt": "m"},
    )
    res = run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", folder)
    one_error(
        res,
        r"mine holds frame_2.ply, frame_999.ply, render4d/mine.txt, which clflow did not write \(the folder has no "
        r"\.clflow-written\.json, the record of clflow's files\) and this run would replace or remove: move them or "
        r"write elsewhere \(-o\)",
    )
    assert "simulating" not in res.stderr and digests(folder) == before
    for name in ("frame_999.ply", "frame_2.ply", "render4d/mine.txt"):
        (folder / name).unlink()
    res = run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", folder)
    one_error(res, r"mine holds render4d/, which clflow did not write")  # an empty folder is the user's too
    (folder / "render4d").rmdir()
    res = run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", folder)
    assert res.returncode == 0, res.stderr
    assert (folder / "notes.txt").read_text() == "n" and (folder / "frame_001.ply").is_file()


def test_simulating_again_replaces_its_frames_and_renders_but_not_what_the_user_changed(quick_demo, tmp_path):
    """The earlier result and what clflow rendered from it (render4d's default folder and one
    of its own, `-o SIM/mine`) go; a frame the user edited since, or a file they added to a
    render folder, is refused."""
    sim = tmp_path / "sim"
    assert run("simulate", quick_demo / "config.yaml", "--set", "simulation.frames=2", "--preview", "none",
               "-o", sim).returncode == 0  # fmt: skip
    for out in ([], ["-o", sim / "mine"]):
        res = run("render4d", sim, *out)
        assert res.returncode == 0, res.stderr
    (sim / "mine" / "notes.txt").write_text("mine")
    before = digests(sim)
    one_error(run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", sim), r"sim holds mine/notes.txt, which")
    (sim / "mine" / "notes.txt").unlink()
    (sim / "frame_002.ply").write_bytes(b"edited")
    one_error(run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", sim), r"sim holds frame_002.ply, which")
    assert digests(sim) == {**{k: v for k, v in before.items() if k != "mine/notes.txt"},
                            "frame_002.ply": hashlib.sha256(b"edited").hexdigest()}  # fmt: skip
    (sim / "frame_002.ply").unlink()
    res = run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", sim)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in sim.iterdir()) == [WRITTEN_RECORD, "frame_000.ply", "frame_001.ply", "gaussians.npz"]


def test_a_particle_simulation_never_overwrites_its_own_particles(tmp_path):
    out = tmp_path / "pp"
    assert run("simulate", "--grid", 16, "--frames", 1, "--preview", "none", "-o", out).returncode == 0
    before = digests(out)
    res = run("simulate", out / "positions.npz", "--grid", 16, "--frames", 1, "--preview", "none", "-o", out)
    one_error(res, r"pp/positions.npz is an input of this run and one of its outputs: write elsewhere \(-o\)")
    assert digests(out) == before


def test_optimize_leaves_a_users_page_in_its_output_folder(quick_demo, tmp_path):
    before = user_folder(tmp_path / "o", {"index.html": "<p>my page</p>", "notes.txt": "n"})
    res = run("optimize", quick_demo / "config.yaml", "-o", tmp_path / "o", "--iterations", 1)
    one_error(res, r"o holds index.html, which clflow did not write")
    assert "iteration" not in res.stderr and digests(tmp_path / "o") == before


def sigint_as_a_terminal_sends_it() -> None:
    """In the child: SIGINT's default action, which Python turns into KeyboardInterrupt (a
    shell ignores SIGINT in the background jobs it starts, and children inherit that)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupted(args: list, when: str, sig: int) -> subprocess.CompletedProcess:
    """``clflow *args``, sent ``sig`` at its first output line that starts with ``when``."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "clflow_cli", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=sigint_as_a_terminal_sends_it,
    )
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith(when):
            break
    proc.send_signal(sig)
    rest, _ = proc.communicate(timeout=300)
    return subprocess.CompletedProcess(proc.args, proc.returncode, "", "".join(seen) + rest)


# SIGTERM takes Ctrl-C's path (cli/main.py raises KeyboardInterrupt for it, and the writes hold
# both alike: clflow.fileio.writing.HELD_SIGNALS; tests/test_cli.py holds a SIGTERM mid-run):
# the two whole-command stops below send INT, and KILL, which nothing can handle
STOPS = pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["INT", "KILL"])


@STOPS
def test_an_interruption_while_optimize_writes_its_results_leaves_none_of_them(quick_demo, tmp_path, sig):
    """The grid check and the writing are one step: interrupted there, no result is written
    (the checkpoint holds every iteration) and the command printed writes them all."""
    out = tmp_path / "o"
    res = _interrupted(
        ["optimize", quick_demo / "config.yaml", "-o", out, "--iterations", 2],
        "checking the result and writing it",
        sig,
    )
    assert not [name for pattern in RESULTS for name in out.glob(pattern)], sorted(out.iterdir())
    assert (out / "checkpoint.json").is_file()
    again = f"clflow optimize {quick_demo / 'config.yaml'} --resume -o {out} --iterations 2"
    if sig != signal.SIGKILL:
        one_error(res, rf"interrupted while checking and writing the results, none of which were written; the 2 "
                       rf"iterations are saved in .*checkpoint.json: write them with `{again}`",
                  exit_code=130)  # fmt: skip
    res = run(*again.split()[1:])
    assert res.returncode == 0, res.stderr
    assert all(list(out.glob(pattern)) for pattern in RESULTS if pattern != "search.json")
    assert not leftovers(tmp_path), sorted(tmp_path.rglob("*"))


def test_the_record_lists_what_atomic_writes_put_there_and_nothing_else(tmp_path):
    out = tmp_path / "out"
    atomic_write_text(out / "params.json", "{}")
    with atomic_dir(out, replaces=("frames", "video.mp4")) as tmp:
        (tmp / "frames").mkdir()
        atomic_write_text(tmp / "frames" / "000.png", "a")
        (tmp / "video.mp4").write_text("v")
    (out / "notes.txt").write_text("mine")
    check_output_folder(out, ("params.json", "frames", "video.mp4"))  # all clflow's
    with pytest.raises(Exception, match=r"out holds notes.txt, which clflow did not write"):
        check_output_folder(out, ("*.txt",))
    (out / "video.mp4").write_text("edited")
    with pytest.raises(Exception, match=r"out holds video.mp4, which clflow did not write \(or which changed since\)"):
        with atomic_dir(out, replaces=("frames", "video.mp4")):
            raise AssertionError("refused on entering")
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        WRITTEN_RECORD, "frames", "frames/000.png", "notes.txt", "params.json", "video.mp4"
    ]  # fmt: skip


@STOPS
def test_an_interrupted_simulate_or_render4d_leaves_the_earlier_result_as_it_was(quick_demo, tmp_path, sig):
    sim = tmp_path / "sim"
    assert run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", sim).returncode == 0
    assert run("render4d", sim).returncode == 0
    before = digests(tmp_path)
    exit_code = {signal.SIGINT: 130, signal.SIGKILL: -9}[sig]
    again = ["simulate", quick_demo / "config.yaml", "--set", "simulation.frames=3", "-o", sim]
    res = _interrupted(again, "simulating:", sig)
    assert res.returncode == exit_code and "Traceback" not in res.stderr, res.stderr
    res = _interrupted(["render4d", sim, "--views", 2], "rendering:", sig)
    assert res.returncode == exit_code and "Traceback" not in res.stderr, res.stderr
    left = leftovers(tmp_path)
    assert not left or sig == signal.SIGKILL, left  # Ctrl-C and SIGTERM clean up
    assert {name: digest for name, digest in digests(tmp_path).items() if not leftovers_name(name)} == before
    assert run(*again).returncode == 0 and run("render4d", sim).returncode == 0
    assert not leftovers(tmp_path)  # a killed run's staging folders went with its folders' next write
    assert (sim / "frame_003.ply").is_file() and (sim / "render4d" / "orbit.mp4").is_file()


def test_ctrl_c_while_a_result_moves_in_lands_after_the_whole_result(tmp_path, monkeypatch):
    """The entries of atomic_dir move in one by one: Ctrl-C (or SIGTERM) at the first move
    is held until the last, so the folder holds the whole new result, never a mix."""
    import os

    import clflow.fileio.writing as fileio

    out = tmp_path / "out"
    with atomic_dir(out, replaces=("a", "b")) as tmp:
        for name in "ab":
            (tmp / name).write_text("old")
    real, moves = os.rename, []

    def rename(src, dst):
        if Path(dst).parent == out:  # a move into the folder
            moves.append(dst)
            if len(moves) == 1:
                os.kill(os.getpid(), signal.SIGINT)
        real(src, dst)

    monkeypatch.setattr(fileio.os, "rename", rename)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a background job ignores it)
    try:
        with pytest.raises(KeyboardInterrupt):
            with atomic_dir(out, replaces=("a", "b")) as tmp:
                for name in "ab":
                    (tmp / name).write_text("new")
    finally:
        signal.signal(signal.SIGINT, before)
    assert len(moves) == 2 and [(out / name).read_text() for name in "ab"] == ["new", "new"]


def test_files_written_inside_a_staged_result_are_recorded_once_with_it(tmp_path, monkeypatch):
    """atomic_path inside an atomic_dir's staging folder writes in place and records nothing
    itself (a record per file would make n frames O(n^2)); the result's one record lists
    every file with its digest."""
    import json

    import clflow.fileio.writing as fileio
    from clflow.fileio import content_digest

    out = tmp_path / "render"
    records = []
    monkeypatch.setattr(fileio, "write_record", lambda *a, real=fileio.write_record: records.append(a) or real(*a))
    with atomic_dir(out) as stage:
        for i in range(5):
            atomic_write_text(stage / "frames" / f"{i:03d}.png", f"frame {i}")
        assert not list(stage.rglob(WRITTEN_RECORD)) and not records  # nothing recorded yet
    assert len(records) == 1
    files = json.loads((out / WRITTEN_RECORD).read_text())["files"]
    assert files == {f"frames/{i:03d}.png": content_digest(out / "frames" / f"{i:03d}.png") for i in range(5)}
    atomic_write_text(out / "frames" / "005.png", "frame 5")  # outside a staging folder: recorded at once
    assert "005.png" in json.loads((out / "frames" / WRITTEN_RECORD).read_text())["files"]


def test_the_material_query_writes_its_guidance_frame_beside_a_users_files_never_over_them(quick_demo, tmp_path):
    """A query without an image writes the guidance video's first frame into the output
    folder (and its record); a user's files there stay, and a user's file of that name is
    refused in one line before the query is asked."""
    from clflow.errors import InputError
    from clflow.pipeline.material import GUIDANCE_FRAME, resolve_material
    from tests.pipeline.test_material import query_config

    out = tmp_path / "out"
    mine = user_folder(out, {"notes.txt": "mine", "plots/a.txt": "a"})
    cfg = query_config(quick_demo, tmp_path, {"type": "query", "query": {"prompt": "a jelly cube"}})
    resolve_material(cfg)
    after = digests(out)
    assert {n: d for n, d in after.items() if n in mine} == mine
    assert {GUIDANCE_FRAME, "material_query.json", WRITTEN_RECORD} == set(after) - set(mine)
    resolve_material(cfg)  # again: it replaces what it wrote (the record: with the new files' fingerprints)
    assert {n: d for n, d in digests(out).items() if n != WRITTEN_RECORD} == {
        n: d for n, d in after.items() if n != WRITTEN_RECORD
    }

    (out / GUIDANCE_FRAME).write_bytes(b"my own picture")
    before = digests(out)
    with pytest.raises(InputError, match=rf"out holds {GUIDANCE_FRAME}, which clflow did not write"):
        resolve_material(cfg)
    assert digests(out) == before


# the query's frame is written (imwrite into atomic_path's temporary) and then the run is
# stopped by ``sig`` before the file moves in, its signal handling a command's: the earlier
# frame must stay as it was
_STOPPED_WHILE_WRITING = """
import os, signal, sys, time
import cv2
from clflow.pipeline.material import resolve_material
from clflow.scene.config import load_config

imwrite = cv2.imwrite
def stalled(path, image):
    ok = imwrite(path, image[::2])  # other bytes than the earlier frame's: a write in place would show
    print("written", flush=True)
    time.sleep(60)
    return ok
cv2.imwrite = stalled
from clflow_cli.main import _SigtermAsInterrupt

signal.signal(signal.SIGINT, signal.default_int_handler)
_SigtermAsInterrupt.install()  # as every clflow command has it
resolve_material(load_config(sys.argv[1]))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["INT", "TERM", "KILL"])
def test_a_query_stopped_while_it_writes_its_frame_leaves_the_earlier_one(quick_demo, tmp_path, sig):
    from clflow.pipeline.material import GUIDANCE_FRAME, resolve_material
    from tests.pipeline.test_material import query_config

    cfg = query_config(quick_demo, tmp_path, {"type": "query", "query": {"prompt": "a jelly cube"}})
    resolve_material(cfg)
    (cfg.output / "notes.txt").write_text("mine")
    before = digests(tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-c", _STOPPED_WHILE_WRITING, str(cfg.source)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdout.readline().strip() == "written"
    proc.send_signal(sig)
    proc.communicate(timeout=60)
    assert proc.returncode != 0
    left = leftovers(tmp_path)
    assert not left or sig == signal.SIGKILL, left  # Ctrl-C and SIGTERM clean up
    assert {n: d for n, d in digests(tmp_path).items() if not leftovers_name(n)} == before
    assert (cfg.output / GUIDANCE_FRAME).is_file()
