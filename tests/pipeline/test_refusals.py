"""Probes of refusals, driven through the CLI as a user would: no retry loop that changes
nothing (a hang), no check that comes after the work it could have spared, no plan printed
that is not the plan run, and one error line that names the file or key and the problem."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from tests._helpers import run_python
from tests.pipeline.test_bad_input import Case, Probe, assert_probe, deep_json, simulation  # noqa: F401 (a fixture)
from tests.scene.test_config import alias_bomb, nested_block


def run(*args, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "clflow_cli", *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def one_error(res: subprocess.CompletedProcess, pattern: str, exit_code: int = 1) -> str:
    """The one error line of ``res``, matching ``pattern``, no traceback; returns stderr."""
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error")]
    assert res.returncode == exit_code and len(errors) == 1, res.stderr
    assert re.search(pattern, errors[0]), errors[0]
    assert "Traceback" not in res.stderr
    return res.stderr


def progress_past_total(stderr: str) -> list[str]:
    """The progress lines ("label: k/total ...") whose count ran past its total."""
    counts = re.findall(r"^\w[\w ]*: (\d+)/(\d+)", stderr, re.M)
    return [f"{k}/{total}" for k, total in counts if int(k) > int(total)]


# -- 1. no hang: every retry changes something or stops ---------------------------------------


def test_a_fixed_substep_that_breaks_the_cfl_limit_mid_run_stops(quick_demo, tmp_path):
    """substep_dt 0.005 s is stable at the demo's start and breaks the CFL limit at frame 4: a
    retry at "twice the substeps" would run the same fixed step forever."""
    res = run(
        "simulate", quick_demo / "config.yaml", "-o", tmp_path / "s", "--preview", "none",
        "--set", "simulation.substep_dt=0.005", timeout=120,
    )  # fmt: skip
    one_error(res, r"breaks the CFL limit .*simulation.substep_dt = 0.005 s is fixed: a shorter one, or auto")
    assert "simulating again" not in res.stderr and not progress_past_total(res.stderr)
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("dt", ["0.02", "10"])
def test_a_fixed_substep_above_the_stable_step_is_refused_before_the_run(quick_demo, tmp_path, dt):
    res = run(
        "simulate", quick_demo / "config.yaml", "-o", tmp_path / "s", "--preview", "none",
        "--set", f"simulation.substep_dt={dt}", timeout=120,
    )  # fmt: skip
    one_error(
        res,
        rf"simulation.substep_dt = {dt} s is above the stable step 0.00833 s of the starting parameters "
        r"\(elastic wave speed .*\); the run would blow up or break the CFL limit: use substep_dt: auto",
    )
    assert "simulating:" not in res.stderr and "StabilityWarning" not in res.stderr


def test_an_unstable_substep_count_of_particles_is_refused_before_the_run(tmp_path):
    res = run(
        "simulate", "--substeps", 1, "--frames", 4, "--grid", 16, "-p", "youngs_modulus=1e6", "-o", tmp_path / "p"
    )
    one_error(res, r"--substeps 1 \(dt = 0.0417 s\) is above the stable step .* \(elastic wave speed .*: 46 substeps")
    assert "simulating:" not in res.stderr and not (tmp_path / "p").exists()


def test_the_progress_never_runs_past_its_total_after_a_cfl_retry(quick_demo, tmp_path):
    res = run("-v", "simulate", quick_demo / "config.yaml", "-o", tmp_path / "s", "--preview", "none")
    assert res.returncode == 0, res.stderr
    assert "simulating again at 10 substeps per frame" in res.stderr  # the demo's start breaks the CFL limit
    assert not progress_past_total(res.stderr)
    assert res.stderr.count("simulating: 8/8") == 1


# -- 2. the plan printed is the plan run; checks before the work ------------------------------


def test_the_plan_printed_is_the_substeps_of_the_params_record(quick_demo, tmp_path):
    record = {"material": "elastic", "parameters": {"youngs_modulus": 2e4}, "density": 1000.0, "substeps": 20}
    (tmp_path / "params.json").write_text(json.dumps({**record, "fps": 24.0, "velocity": [0, 0, 0]}))
    res = run(
        "simulate", quick_demo / "config.yaml", "--params-from", tmp_path / "params.json", "-o", tmp_path / "s",
        "--preview", "none",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert re.search(r"simulation: 20 substeps per frame", res.stderr), res.stderr


def no_scene(c: Case) -> None:
    """Loading the scene fails the probe: the refusal must come before it."""

    def loaded(*args, **kwargs):
        raise AssertionError("the scene was loaded before the refusal")

    c.monkeypatch.setattr("clflow.pipeline.forward.load_scene_objects", loaded)


def no_ply(c: Case) -> None:
    """Reading a PLY fails the probe: the refusal must come before it."""

    def read(*args, **kwargs):
        raise AssertionError("the PLY was read before the refusal")

    c.monkeypatch.setattr("clflow.splat.load_ply", read)


def particles(c: Case, **arrays) -> str:
    path = c.tmp / "parts.npz"
    np.savez(path, positions=np.random.default_rng(0).random((50, 3)) * 0.2 + 0.4, **arrays)
    return str(path)


def changed_resume(c: Case) -> str:
    """A config whose output holds the checkpoint of a run of it (its config digests)."""
    from clflow.pipeline.fit.state import config_digests
    from clflow.scene.config import load_config

    path = c.config("resume_changed")
    (c.tmp / "out").mkdir()
    (c.tmp / "out" / "checkpoint.json").write_text(json.dumps({"config_digests": config_digests(load_config(path))}))
    return path


def params_json(c: Case, **parameters) -> str:
    path = c.tmp / "params.json"
    path.write_text(json.dumps({"material": "elastic", "parameters": parameters, "density": 1000.0}))
    return str(path)


def case_file(c: Case, name: str, text: str) -> str:
    (c.tmp / name).write_text(text)
    return str(c.tmp / name)


def deep_checkpoint(c: Case) -> str:
    """A config whose output holds a checkpoint.json nested 200,000 levels deep."""
    path = c.config("resume_deep")
    (c.tmp / "out").mkdir()
    deep_json(c, "out/checkpoint.json")
    return path


BEFORE_WORK = [
    # options that do not apply to the input kind, values out of the documented range
    Probe(
        "simulate-particle-file-with-shape-options",
        lambda c: ["simulate", particles(c), "--shape", "torus", "--size", 0.1, "-o", c.tmp / "s"],
        r"parts.npz has its own particles, not a built-in shape: drop --shape, --size",
        ("s",),
        exit_code=2,
    ),
    Probe(
        "simulate-shape-with-particle-volume",
        lambda c: ["simulate", "--particle-volume", 1e-6, "-o", c.tmp / "s"],
        r"--particle-volume applies to a PARTICLES file, not to a built-in shape",
        ("s",),
        exit_code=2,
    ),
    Probe(
        "simulate-volumes-given-twice",
        lambda c: ["simulate", particles(c, volume=np.full(50, 1e-6)), "--particle-volume", 1e-6, "-o", c.tmp / "s"],
        r"parts.npz gives each particle's 'volume': drop --particle-volume",
        ("s",),
    ),
    Probe(
        "render-camera-file-with-new-view-options",
        lambda c: ["render", c.demo / "scene.ply", "--transforms", c.tmp / "t.json", "--width", 1024, "--fov", 10],
        r"--fov, --width make new views, --cameras/--transforms give theirs: drop them",  # ignored before
        setup=no_ply,
        exit_code=2,
    ),
    Probe(
        "reconstruct-a-photo-with-training-options",
        lambda c: ["reconstruct", c.demo / "guidance" / "000.png", "--depth", "d.npy", "--iterations", 5, "-o", c.tmp],
        r"with --depth nothing is trained: drop --iterations",  # ignored before
        exit_code=2,
    ),
    Probe(
        "reconstruct-training-with-photo-options",
        lambda c: ["reconstruct", c.demo / "guidance", "--fov", 30, "-o", c.tmp / "r"],
        r"they go with --depth \(a photo and its depth map\): drop --fov",
        ("r",),
        exit_code=2,
    ),
    Probe(
        "render-background-out-of-range",
        lambda c: ["render", c.demo / "scene.ply", "--background", "2,2,2", "-o", c.tmp / "r"],
        r"Invalid value for '--background': '2,2,2': each number must be in \[0, 1\]",
        ("r",),
        no_ply,
        exit_code=2,
    ),
    # checks that came after the scene was read, prepared or run
    Probe(
        "render-too-much-output-before-the-ply",
        lambda c: ["render", c.demo / "scene.ply", "--orbit", 100000, "--width", 4096, "-o", c.tmp / "r"],
        r"would write up to 629 GB \(100,000 views\), more than --max-output-gb 10",
        ("r",),
        no_ply,
    ),
    Probe(
        "optimize-resume-with-a-changed-set",
        lambda c: ["optimize", changed_resume(c), "--resume", "--set", "material.parameters.poissons_ratio=0.35"],
        r"cannot resume from .*checkpoint.json: the config changed since it was saved \(material\)",
        setup=no_scene,
    ),
    Probe(
        "optimize-without-video",
        lambda c: ["optimize", c.config("novideo", video=None)],
        r"novideo.yaml: video is required to optimise",
        ("out",),
        no_scene,
    ),
    Probe(
        "params-json-negative-modulus",
        lambda c: ["simulate", c.config("p"), "--params-from", params_json(c, youngs_modulus=-5), "-o", c.tmp / "s"],
        r"params.json: youngs_modulus \(E\) = -5 Pa is outside the valid range",
        ("s",),
        no_scene,
    ),
    Probe(
        "camera-position-is-look-at",
        lambda c: ["simulate", c.config("eye", **{"camera.position": [0.0, 0.1, 0.0]}), "-o", c.tmp / "s"],
        r"eye.yaml: camera.position and camera.look_at are the same point \[0.0, 0.1, 0.0\]$",
        ("s",),
        no_scene,
    ),
    # files that do not parse, or hold nothing: one line saying so
    Probe(
        "config-alias-bomb",
        lambda c: ["simulate", case_file(c, "bomb.yaml", (c.demo / "config.yaml").read_text() + alias_bomb(8))],
        r"bomb.yaml: bomb.a5: more than 100,000 nodes \(lists, mappings, keys and values\) with its aliases expanded",
        setup=no_scene,
    ),
    Probe(
        "config-yaml-nested-5000-deep",
        lambda c: ["simulate", case_file(c, "deep.yaml", "splats: scene.ply\n" + nested_block(5000, "-"))],
        r"deep.yaml: nested deeper than 100 levels \(line 102, column 201\)$",
    ),
    Probe(
        "config-json-nested-100000-deep",
        lambda c: ["simulate", case_file(c, "deep.json", '{"splats": ' + "[" * 100_000 + "]" * 100_000 + "}")],
        r"deep.json: nested deeper than 100 levels \(line 1, column 111\)$",
    ),
    Probe(
        "params-json-nested-200000-deep",
        lambda c: ["simulate", c.config("p"), "--params-from", deep_json(c, "params.json")],
        r"params.json: nested deeper than 100 levels \(line 1, column 106\); expected the params.json",
        setup=no_scene,
    ),
    Probe(
        "optimize-resume-from-a-checkpoint-nested-200000-deep",
        lambda c: ["optimize", deep_checkpoint(c), "--resume"],
        r"cannot resume from .*checkpoint.json: nested deeper than 100 levels \(line 1, column 106\)$",
        setup=no_scene,
    ),
    Probe(
        "config-empty-with-a-set",
        lambda c: ["simulate", case_file(c, "empty.yaml", "# nothing yet\n"), "--set", "simulation.frames=2"],
        r"empty.yaml: the config file is empty$",
    ),
    Probe(
        "config-yaml-syntax",
        lambda c: ["simulate", case_file(c, "broken.yaml", "splats: [scene.ply\n")],
        r"broken.yaml: not valid YAML: line 2, column 1: expected ',' or '\]', but got '<stream end>'$",
    ),
    Probe(
        "sysid-cases-yaml-syntax",
        lambda c: ["eval", "sysid", "--cases", case_file(c, "c.yaml", "jelly:\n  size: [0.5\n"), "-o", c.tmp / "o"],
        r"c.yaml: not valid YAML: line 3, column 1",
        ("o",),
    ),
    Probe(
        "sysid-cases-truncated-json",
        lambda c: ["eval", "sysid", "--cases", case_file(c, "c.json", '{"jelly": {"size": 0.5, '), "-o", c.tmp / "o"],
        r"c.json: not valid JSON: line 1, column 25: Expecting property name",
        ("o",),
    ),
    Probe(
        "sysid-cases-size-0",
        lambda c: [
            "eval",
            "sysid",
            "-o",
            c.tmp / "o",
            "--cases",
            case_file(c, "c.yaml", "jelly: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, size: 0}"),
        ],
        r"c.yaml: jelly.size: must be in \(0, 10000\], got 0$",
        ("o",),
    ),
    Probe(
        "sysid-cases-missing",
        lambda c: ["eval", "sysid", "--cases", c.tmp / "missing.yaml", "-o", c.tmp / "o"],
        r"^Error: case file \S*missing.yaml not found$",  # not "not YAML or JSON"
        ("o",),
    ),
    Probe(
        "simulate-a-txt",
        lambda c: ["simulate", case_file(c, "cfg.txt", "splats: scene.ply\n"), "-o", c.tmp / "s"],
        r"cfg.txt: not a particle file or a scene config \(the file name must end in .npz, .ply, .yaml, .yml, .json\)",
        ("s",),
    ),
    Probe(
        "render-empty-ply",
        lambda c: ["render", empty_ply(c), "-o", c.tmp / "r"],
        r"empty.ply: holds no Gaussians$",
        ("r",),
    ),
    Probe(
        "render-transforms-missing-image",
        lambda c: ["render", c.demo / "scene.ply", "--transforms", missing_image_transforms(c), "-o", c.tmp / "r"],
        r"transforms.json: frames\[0\]: image .*gone\[.png\] not found \(no 'w', 'h': its size is needed\)$",
        ("r",),
    ),
    Probe(
        "flow-stride-0",
        lambda c: ["flow", c.demo / "guidance", "--stride", 0, "-o", c.tmp / "f"],
        r"Invalid value for '--stride': 0 is not in the range x>=1",  # exit 1 after reading the frames before
        ("f",),
        exit_code=2,
    ),
    # the words: what is wrong, named as the user gave it
    Probe(
        "flow-window-of-an-image-folder",
        lambda c: ["flow", c.demo / "guidance", "--end", 0.2, "-o", c.tmp / "f"],
        r"guidance is an image folder, which has no frame rate: --end needs --fps",  # not "pass fps= ..."
        ("f",),
        exit_code=2,
    ),
    Probe(
        "query-port-out-of-range",
        lambda c: [
            "query",
            c.demo / "guidance" / "000.png",
            "--backend",
            "openai",
            "--llm-url",
            "http://127.0.0.1:99999",
            "--model",
            "m",
            "-o",
            c.tmp / "q.json",
        ],
        r"--llm-url 'http://127.0.0.1:99999': the port must be a number from 1 to 65535$",
        ("q.json",),
    ),
    Probe(
        "simulate-query-openai-without-url",
        lambda c: [
            "simulate",
            "-o",
            c.tmp / "s",
            c.config(
                "query",
                material={"type": "query", "query": {"image": "guidance/000.png", "backend": "openai"}},
                evaluation=None,
            ),
        ],
        r"query.yaml: material.query.backend: openai needs an endpoint: set \$CLFLOW_LLM_URL$",
        ("s",),
        lambda c: [c.monkeypatch.delenv(n, raising=False) for n in ("CLFLOW_LLM_URL", "OPENAI_BASE_URL")],
    ),
]


def empty_ply(c: Case) -> str:
    import torch

    from clflow.splat.ply import load_ply, save_ply

    save_ply(c.tmp / "empty.ply", load_ply(c.demo / "scene.ply").select(torch.zeros(0, dtype=torch.long)))
    return str(c.tmp / "empty.ply")


def missing_image_transforms(c: Case) -> str:
    frame = {"file_path": "gone", "transform_matrix": np.eye(4).tolist()}
    (c.tmp / "transforms.json").write_text(json.dumps({"camera_angle_x": 1.0, "frames": [frame]}))
    return str(c.tmp / "transforms.json")


@pytest.mark.parametrize("probe", BEFORE_WORK, ids=[p.id for p in BEFORE_WORK])
def test_refused_in_one_line_before_the_work(probe, quick_demo, simulation, tmp_path, monkeypatch):  # noqa: F811
    output = assert_probe(probe, Case(quick_demo, simulation, tmp_path, monkeypatch))
    assert len(output.strip().splitlines()) == 1, output  # the error line alone: nothing ran before it


# -- 3. no stray lines ------------------------------------------------------------------------


def test_torchs_info_lines_stay_out_of_a_commands_output():
    """torch logs "FakeTensor cache stats" at exit, at INFO, when a Ctrl-C cut its import short
    (before it set its loggers' levels): three lines after the error."""
    code = (
        "import logging\n"
        "from clflow_cli.main import cli\n"
        "try:\n"
        "    cli(['devices', '--help'])\n"  # the root command set the logging up
        "except SystemExit:\n"
        "    pass\n"
        "logging.getLogger('torch._subclasses.fake_tensor').info('FakeTensor cache stats:')\n"
        "logging.getLogger('clflow').info('a line of clflow')\n"
    )
    res = run_python(code)
    assert "FakeTensor" not in res.stderr and "a line of clflow" in res.stderr
