"""Nothing of the user's is touched, through the CLI as a user would: not beside the output
folder, not by two runs into one folder at once, not under a cache's name, not through a
link to nothing. Exit status and one error line before any work; the user's files hashed
before and after."""

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.pipeline.test_refusals import one_error, run
from tests.pipeline.test_written_record import digests

SIMULATE = ("--set", "simulation.frames=1", "--preview", "none")


def _look_alikes(folder):
    """A user's files and folders whose names look like temporaries (a pid no process has)."""
    (folder / ".photos.2023.summer.tmp").mkdir(parents=True)
    (folder / ".photos.2023.summer.tmp" / "img1.jpg").write_bytes(b"jpeg")
    (folder / ".notes.99999.v2.tmp.txt").write_text("notes")
    (folder / ".draft.31337.final.tmp").write_text("draft")
    return digests(folder)


def test_simulate_leaves_files_beside_its_output_that_look_like_temporaries(quick_demo, tmp_path):
    before = _look_alikes(tmp_path)
    for _ in range(2):  # a first run, and one over its result
        res = run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", tmp_path / "XK")
        assert res.returncode == 0, res.stderr
    after = digests(tmp_path)
    assert {n: d for n, d in after.items() if n in before} == before


def _started(*args, until: str) -> subprocess.Popen:
    """``clflow *args``, returned stopped (SIGSTOP) once it printed a line that starts with
    ``until``: it holds its output folder until continued (SIGCONT), however fast the run."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "clflow_cli", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    for line in proc.stdout:
        if line.startswith(until):
            proc.send_signal(signal.SIGSTOP)
            return proc
    raise AssertionError(f"clflow {' '.join(map(str, args))} ended before {until!r}")


def test_a_second_simulate_into_a_folder_being_written_is_refused_naming_the_first(quick_demo, tmp_path):
    out = tmp_path / "C2"
    first = _started("simulate", quick_demo / "config.yaml", "--set", "simulation.frames=6", "-o", out,
                     until="simulating:")  # fmt: skip
    second = run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", out)
    one_error(second, r"C2 is being written by another clflow run \(`clflow simulate .*`, pid \d+ on .*, since .*\): "
                      r"let it finish, write elsewhere \(-o\), or run with `clflow --wait \.\.\.` to wait for it")  # fmt: skip
    assert "simulating" not in second.stderr
    first.send_signal(signal.SIGCONT)
    first.communicate(timeout=600)
    assert first.returncode == 0
    assert sorted(p.name for p in out.glob("frame_*.ply")) == [f"frame_{k:03d}.ply" for k in range(7)]
    waited = run("--wait", "simulate", quick_demo / "config.yaml", *SIMULATE, "-o", out)
    assert waited.returncode == 0, waited.stderr  # the first is done: the next run replaces its result whole
    assert sorted(p.name for p in out.glob("frame_*.ply")) == ["frame_000.ply", "frame_001.ply"]


def test_a_second_optimize_into_a_running_ones_folder_is_refused_and_its_result_stays(quick_demo, tmp_path):
    out = tmp_path / "OC"
    first = _started("optimize", quick_demo / "config.yaml", "-o", out, "--iterations", 14, until="iteration 1/")
    second = run("optimize", quick_demo / "config.yaml", "-o", out, "--iterations", 3)
    one_error(second, r"OC is being written by another clflow run \(`clflow optimize .*--iterations 14`")
    first.send_signal(signal.SIGINT)
    first.send_signal(signal.SIGCONT)
    first.communicate(timeout=300)
    assert (out / "checkpoint.json").is_file()  # the first run's, resumable: not replaced by the second


@pytest.mark.parametrize("name", ["estimator_error.npz", "observed_flow.npz"])
@pytest.mark.parametrize("kind", ["text", "npz"])
def test_optimize_refuses_a_users_file_under_a_cache_name_before_any_work(quick_demo, tmp_path, name, kind):
    out = tmp_path / "o"
    out.mkdir()
    if kind == "text":
        (out / name).write_text("my notes")
    else:
        np.savez(out / name, mine=np.arange(3))
    before = digests(out)
    res = run("optimize", quick_demo / "config.yaml", "-o", out, "--iterations", 1)
    one_error(res, rf"o holds {name}, which clflow did not write")
    assert "iteration" not in res.stderr and digests(out) == before


@pytest.mark.parametrize("command", ["simulate", "optimize", "render4d"])
def test_an_output_that_is_a_link_to_nothing_is_refused_before_any_work(quick_demo, tmp_path, command):
    (tmp_path / "DL").symlink_to(tmp_path / "nowhere")
    source = {"simulate": quick_demo / "config.yaml", "optimize": quick_demo / "config.yaml"}
    if command == "render4d":
        assert run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", tmp_path / "sim").returncode == 0
        source[command] = tmp_path / "sim"
    started = time.perf_counter()
    res = run(command, source[command], "-o", tmp_path / "DL")
    one_error(res, r"DL is a symbolic link to .*nowhere, which does not exist: make it, or write elsewhere \(-o\)")
    assert "simulating" not in res.stderr and "iteration" not in res.stderr and "rendering" not in res.stderr
    assert time.perf_counter() - started < 60 and not (tmp_path / "nowhere").exists()


def test_an_output_file_of_the_users_is_refused_before_any_work(quick_demo, tmp_path):
    """Files named on the command line (a video, a profile) are written over only when clflow wrote them."""
    mine = tmp_path / "mine.mp4"
    mine.write_bytes(b"my video")
    res = run("render", quick_demo / "scene.ply", "-o", tmp_path / "views", "--video", mine)
    one_error(res, r"holds mine.mp4, which clflow did not write")
    res = run("--profile", mine, "simulate", "--frames", 1, "--grid", 16, "--preview", "none", "-o", tmp_path / "s")
    one_error(res, r"holds mine.mp4, which clflow did not write")
    assert mine.read_bytes() == b"my video" and not (tmp_path / "views").exists() and not (tmp_path / "s").exists()


def test_links_and_empty_folders_put_into_a_rendering_are_refused_not_removed(quick_demo, tmp_path):
    """A link to a folder, a link to a file and an empty folder that a user put into a
    rendering clflow derived from a simulation: simulating there again refuses each, by one rule."""
    sim = tmp_path / "sim"
    assert run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", sim).returncode == 0
    assert run("render4d", sim).returncode == 0
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.jpg").write_bytes(b"jpeg")
    (sim / "render4d" / "to_folder").symlink_to(tmp_path / "photos")
    (sim / "render4d" / "to_file").symlink_to(tmp_path / "photos" / "a.jpg")
    (sim / "render4d" / "empty").mkdir()
    res = run("simulate", quick_demo / "config.yaml", *SIMULATE, "-o", sim)
    one_error(res, r"sim holds render4d/to_file, render4d/to_folder, render4d/empty/, which clflow did not write")
    assert (tmp_path / "photos" / "a.jpg").read_bytes() == b"jpeg" and (sim / "render4d" / "empty").is_dir()
