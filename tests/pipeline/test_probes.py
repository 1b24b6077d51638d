"""Probes of bad input, run through the CLI as a user would, a row each: every class of bad
input ends with exit status 1 (a bad input) or 2 (a wrong command line), one line, no
traceback, before any work, and leaves nothing behind or the earlier result intact. Then
what is left behind or mixed after a crash, a failure or a re-run, and a seeded fuzz pass
over config values."""

import json
import math
import random
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from clflow.fileio import WRITTEN_RECORD, atomic_write_text
from clflow_cli.main import cli
from tests.pipeline.test_bad_input import Case, Probe, assert_probe, simulation  # noqa: F401 (a fixture)

LATIN1_COMMENT = "\n# café\n".encode("latin-1")


def not_utf8_config(c: Case) -> str:
    """The demo's config plus one Latin-1 comment line (as an editor on another system saves it)."""
    path = c.demo / "latin1.yaml"
    path.write_bytes(open(c.config("latin1"), "rb").read() + LATIN1_COMMENT)
    return str(path)


def random_bytes(c: Case, name: str) -> str:
    path = c.tmp / name
    path.write_bytes(np.random.default_rng(7).bytes(400))
    return str(path)


def gap_in_guidance(c: Case) -> str:
    """The demo's guidance frames with 002.png removed."""
    shutil.copytree(c.demo / "guidance", c.demo / "gap_guidance", dirs_exist_ok=True)
    (c.demo / "gap_guidance" / "002.png").unlink(missing_ok=True)
    return c.config("gap", video="gap_guidance")


def params_json(c: Case, **record) -> str:
    path = c.tmp / "params.json"
    path.write_text(json.dumps(record))
    return str(path)


PROBES = [
    # tracebacks before: a file that is not UTF-8 text
    Probe(
        "optimize-config-latin1",
        lambda c: ["optimize", not_utf8_config(c)],
        r"config .*latin1.yaml is not UTF-8 text \(byte 0xe9 on line \d+\); save it as UTF-8",
        ("out",),
    ),
    Probe(
        "simulate-config-random-bytes",
        lambda c: ["simulate", random_bytes(c, "noise.yaml"), "-o", c.tmp / "s"],
        r"config .*noise.yaml is not UTF-8 text",
        ("s",),
    ),
    Probe(
        "sweep-spec-random-bytes",
        lambda c: ["sweep", random_bytes(c, "spec.yaml"), "--serial", "-o", c.tmp / "sw"],
        r"sweep spec .*spec.yaml is not UTF-8 text",
        ("sw",),
    ),
    Probe(
        "params-file-random-bytes",
        lambda c: ["simulate", c.config("p"), "--params-from", random_bytes(c, "p.json"), "-o", c.tmp / "s"],
        r"params file .*p.json is not UTF-8 text",
        ("s",),
    ),
    # a wrong command line: one line, exit 2
    Probe(
        "simulate-fps-0",
        lambda c: ["simulate", "--fps", 0, "--frames", 2, "--grid", 16, "-o", c.tmp / "s"],
        r"--fps.*0.0 is not in the range x>0. \(see '.* simulate -h'\)",
        ("s",),
        exit_code=2,
    ),  # fmt: skip
    Probe(
        "simulate-frames-0",
        lambda c: ["simulate", "--frames", 0, "-o", c.tmp / "s"],
        r"--frames.*0 is not in the range x>=1",
        ("s",),
        exit_code=2,
    ),  # fmt: skip
    # silent wrong results before
    Probe(
        "guidance-frame-missing",
        lambda c: ["optimize", gap_in_guidance(c)],
        r"gap_guidance: no frame near t = 0.08333 s: the frames jump from 0.04167 s to 0.125 s .* frames are missing",
        ("out",),
    ),
    Probe(
        "resume-without-checkpoint",
        lambda c: ["optimize", c.config("resume"), "--resume"],
        r"--resume: .*out holds no interrupted run to continue \(no checkpoint.json\)",
        ("out",),
    ),
    # misleading errors before
    Probe(
        "density-1e40",
        lambda c: ["optimize", c.config("dense", **{"material.density": 1e40})],
        r"density \(rho\) = 1e\+40 kg/m\^3 is outside the valid range \[0.001, 1e\+06\]",
        ("out",),
    ),
    Probe(
        "params-json-without-density",
        lambda c: [
            "simulate",
            c.config("nodensity"),
            "--params-from",
            params_json(c, material="elastic", parameters={"youngs_modulus": 3e4}),
            "-o",
            c.tmp / "s",
        ],
        r"params.json lacks 'density': not a params.json of clflow optimize",
        ("s",),
    ),
    Probe(
        "bench-json-in-proc",
        lambda c: ["bench", "mpm", "--particles-per-axis", 4, "--grid", 16, "--json", "/proc/x.json"],
        r"^Error: --json /proc/x.json: /proc is not writable",
    ),
    Probe(
        "render-out-in-proc",
        lambda c: ["render", c.demo / "scene.ply", "-o", "/proc/r"],
        r"^Error: output folder /proc/r: /proc is not writable",
    ),
    Probe(
        "optimize-config-is-a-folder",
        lambda c: ["optimize", c.tmp],
        r"^Error: CONFIG: File .* is a directory",
    ),
    Probe(
        "simulate-out-is-a-file",
        lambda c: ["simulate", "--frames", 1, "-o", c.a_file()],
        r"^Error: output folder .*afile is a file, not a folder",
    ),
    # checked late before: an unreadable video is found before the scene is loaded
    Probe(
        "video-random-bytes",
        lambda c: ["optimize", c.config("noise_video", video=random_bytes(c, "noise.mp4"))],
        r"noise.mp4: not a readable video",
        ("out",),
    ),
]


@pytest.mark.parametrize("probe", PROBES, ids=[p.id for p in PROBES])
def test_bad_input_is_one_line_before_any_work(probe, quick_demo, simulation, tmp_path, monkeypatch):  # noqa: F811
    output = assert_probe(probe, Case(quick_demo, simulation, tmp_path, monkeypatch))
    assert "object:" not in output  # refused before the scene was loaded


def test_the_help_says_what_the_options_take():
    render = CliRunner().invoke(cli, ["render", "--help"]).output
    assert "None" not in render  # no "[x<=None]" for an unbounded number
    sysid = CliRunner().invoke(cli, ["eval", "sysid", "--help"]).output
    assert all(name in " ".join(sysid.split()) for name in ("droplet", "toothpaste", "trophy", "--quick (torus"))


# -- left behind or mixed -------------------------------------------------------------------


def run(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "clflow_cli", *map(str, args)], capture_output=True, text=True, timeout=600
    )


_KILLED_MID_WRITE = """
import sys, time
from clflow.fileio import atomic_dir
with atomic_dir(sys.argv[1], ("positions.npz",)) as new:
    (new / "positions.npz").write_bytes(b"x" * 1000)
    print("staged", flush=True)
    time.sleep(60)
"""


def test_a_killed_simulations_leftovers_go_with_the_next_run_and_look_alikes_stay(tmp_path):
    """kill -9 leaves the staging folder of an unfinished output in it; the next run of the
    same output removes it (its claim can be locked: its writer is gone) instead of keeping
    it forever. Names that only look like temporaries, beside the output or in it, stay."""
    out = tmp_path / "s"
    killed = subprocess.Popen([sys.executable, "-c", _KILLED_MID_WRITE, str(out)], stdout=subprocess.PIPE, text=True)
    assert killed.stdout.readline().strip() == "staged"
    killed.kill()
    killed.wait()
    assert [p.name for p in out.iterdir() if p.name.startswith(".clflow-staging.")]
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    look_alikes = [tmp_path / f".s.{int(dead.stdout)}.abc123.tmp", out / f".s.{int(dead.stdout)}.abc123.tmp"]
    for folder in look_alikes:
        folder.mkdir()
        (folder / "000.png").write_bytes(b"mine")
    res = run("simulate", "--frames", 1, "--grid", 16, "--preview", "none", "-o", out)
    assert res.returncode == 0, res.stderr
    assert not [p.name for p in out.iterdir() if p.name.startswith(".clflow-staging.")]
    assert all((folder / "000.png").read_bytes() == b"mine" for folder in look_alikes)


def test_a_resimulation_replaces_every_frame_and_what_was_rendered_from_them(quick_demo, tmp_path):
    config = tmp_path / "c.yaml"
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    data.update(splats=str(quick_demo / "scene.ply"), video=str(quick_demo / "guidance"))
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "sim"
    assert run("simulate", config, "-o", out, "--preview", "none", "--set", "simulation.frames=4").returncode == 0
    assert run("render4d", out).returncode == 0 and (out / "render4d").is_dir()
    res = run("simulate", config, "-o", out, "--preview", "none", "--set", "simulation.frames=2")
    assert res.returncode == 0, res.stderr
    frames = sorted(p.name for p in out.glob("frame_*.ply"))
    assert frames == ["frame_000.ply", "frame_001.ply", "frame_002.ply"]  # not the 4-frame run's 003, 004
    assert not (out / "render4d").exists()  # rendered from the earlier simulation


def test_a_simulation_that_breaks_the_cfl_limit_runs_again_and_never_exits_0_unstable(quick_demo, tmp_path):
    """The demo's start breaks the CFL limit at its estimated 5 substeps per frame (its push):
    simulate runs it again at twice the substeps instead of warning and carrying on."""
    res = run("-v", "simulate", quick_demo / "config.yaml", "-o", tmp_path / "s", "--preview", "none")
    assert res.returncode == 0, res.stderr
    assert "simulating again at 10 substeps per frame" in res.stderr
    assert "StabilityWarning" not in res.stderr
    assert "compiling kernels" not in res.stderr  # the driver's cache answers: no false "compiling"
    limited = run("simulate", quick_demo / "config.yaml", "-o", tmp_path / "t", "--max-substeps", 6)
    assert limited.returncode == 1 and "breaks the CFL limit" in limited.stderr and "--max-substeps" in limited.stderr
    assert not (tmp_path / "t").exists()


def test_a_failed_first_run_leaves_no_folder_and_a_new_run_never_mixes_with_an_earlier_one(quick_demo, tmp_path):
    config = tmp_path / "c.yaml"
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    data.update(splats=str(quick_demo / "scene.ply"), video=str(quick_demo / "guidance"))
    data["camera"]["look_at"] = [3.0, 3.0, 3.0]  # looks away: the guidance check refuses after the flow
    config.write_text(yaml.safe_dump(data))
    res = run("optimize", config, "-o", tmp_path / "new")
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert not (tmp_path / "new").exists()  # it held only observed_flow.npz
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    for name in ("params.json", "metrics.json", "checkpoint.json", "index.html", "starts/0/checkpoint.json"):
        atomic_write_text(earlier / name, "{}")  # as an earlier run wrote them
    (earlier / "mine.txt").write_text("{}")
    res = run("optimize", config, "-o", earlier)
    assert res.returncode == 1
    assert sorted(p.name for p in earlier.iterdir() if not p.name.startswith(("observed_flow", "estimator"))) == [
        WRITTEN_RECORD,
        "mine.txt",  # not the run's: kept
    ]


def test_a_moved_run_resumes_and_the_hint_repeats_the_options(quick_demo, tmp_path):
    first = tmp_path / "first"
    shutil.copytree(quick_demo, first, ignore=shutil.ignore_patterns("bad_*", "latin1*", "gap_*", "*.npy"))
    res = run("optimize", first / "config.yaml", "--set", "optimize.iterations=1", "-o", first / "results")
    assert res.returncode == 0, res.stderr
    assert "grid check at" not in res.stderr or "failed" not in res.stderr  # it works on the demo
    moved = tmp_path / "moved"
    shutil.move(first, moved)
    again = run("optimize", moved / "config.yaml", "--resume", "--iterations", 2, "-o", moved / "results")
    assert again.returncode == 0, again.stderr  # not "the config changed since it was saved"
    assert json.loads((moved / "results" / "checkpoint.json").read_text())["state"]["iteration"] == 2


# -- fuzz ----------------------------------------------------------------------------------------

ODD_VALUES = [None, "", "abc", [], {}, -1, 0, 1e40, -1e40, math.nan, math.inf, True, [1, 2], "1e3", 2**70]


def scalar_keys(node, prefix=""):
    """Dotted paths of every scalar (and list of numbers) in a config tree."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield from scalar_keys(value, f"{prefix}{key}.")
    else:
        yield prefix[:-1]


@pytest.mark.slow
def test_fuzzed_config_values_end_in_a_clean_run_or_one_line(quick_demo, tmp_path):
    """Seeded: 60 (key, odd value) pairs over the demo config's keys, each through `clflow
    simulate CONFIG --set KEY=VALUE` (one frame): exit 0, or exit 1/2 with one error line;
    never a traceback."""
    data = yaml.safe_load((quick_demo / "config.yaml").read_text())
    keys = sorted(set(scalar_keys(data)) - {"output", "video", "splats"})
    rng = random.Random(32)
    outcomes = []
    for k in range(60):
        key, value = rng.choice(keys), rng.choice(ODD_VALUES)
        setting = f"{key}={yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()}"
        res = CliRunner().invoke(
            cli,
            ["simulate", str(quick_demo / "config.yaml"), "-o", str(tmp_path / f"s{k}"), "--preview", "none",
             "--set", "simulation.frames=1", "--set", setting],
        )  # fmt: skip
        crashed = res.exception is not None and not isinstance(res.exception, SystemExit)
        errors = [line for line in res.output.splitlines() if line.startswith("Error")]
        assert not crashed, f"--set {setting}: {res.exception!r}"
        assert res.exit_code == 0 or (res.exit_code in (1, 2) and len(errors) == 1), f"--set {setting}: {res.output}"
        outcomes.append(res.exit_code)
    assert 0 in outcomes and 1 in outcomes  # the sample holds clean runs and refusals
