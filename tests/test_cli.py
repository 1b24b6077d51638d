"""The CLI skeleton: lazy imports, version, devices, device selection errors."""

import json
import os
import subprocess
import sys

import click
import pytest
from click.testing import CliRunner

from clflow import __version__
from clflow.fileio import atomic_write_text
from clflow_cli.main import BUILTIN_COMMANDS, cli
from tests._helpers import run_python


def test_help_and_every_command_help_import_neither_torch_nor_opencl():
    # `clflow --help` must be instant: listing commands imports their modules, which may
    # import only click at module level.
    code = (
        "import sys\n"
        "from click.testing import CliRunner\n"
        "from clflow_cli.main import cli, BUILTIN_COMMANDS\n"
        "r = CliRunner().invoke(cli, ['--help']); assert r.exit_code == 0, r.output\n"
        "for name in BUILTIN_COMMANDS:\n"
        "    r = CliRunner().invoke(cli, [name, '--help']); assert r.exit_code == 0, (name, r.output)\n"
        "heavy = sorted(m for m in ('torch', 'pyopencl', 'cv2', 'numpy', 'kornia') if m in sys.modules)\n"
        "print(heavy)\n"
    )
    res = run_python(code)
    assert res.stdout.strip() == "[]"


@pytest.mark.parametrize("preset,expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_cli_lets_torch_openmp_threads_sleep_unless_told_otherwise(preset, expected):
    # set before torch loads (the commands import it lazily), so libgomp sees it
    code = "import os, sys; import clflow_cli.main; assert 'torch' not in sys.modules; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset:
        env["OMP_WAIT_POLICY"] = preset
    res = run_python(code, env=env)
    assert res.stdout.strip() == expected


def test_help_lists_the_builtin_commands():
    out = CliRunner().invoke(cli, ["--help"]).output
    for name in BUILTIN_COMMANDS:
        assert name in out


def test_version():
    res = CliRunner().invoke(cli, ["--version"])
    assert res.exit_code == 0 and __version__ in res.output


def test_devices_lists_the_capabilities(device):
    res = CliRunner().invoke(cli, ["devices"])
    assert res.exit_code == 0, res.output
    for field in ("fp64", "float atomics", "unified memory", "compute units", "kernel cache dir", "OpenCL C"):
        assert field in res.output
    assert f"* {device.info.label}" in res.output


def test_devices_json(device):
    res = CliRunner().invoke(cli, ["devices", "--json"])
    data = json.loads(res.output)
    assert any(d["selected"] and d["name"] == device.info.name for d in data["devices"])


def test_unknown_device_is_a_clear_error(monkeypatch):
    from clflow.runtime import devices as devmod

    monkeypatch.setattr(devmod, "_DEFAULT_SPEC", None)
    res = CliRunner().invoke(cli, ["--device", "no-such-gpu", "devices"])
    monkeypatch.setattr(devmod, "_DEFAULT_SPEC", None)
    assert res.exit_code == 1
    assert "no OpenCL device matches 'no-such-gpu'" in res.output and "available devices" in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)


class _InterruptedOptimization:
    """Stands in for clflow.pipeline.fit.Optimization: Ctrl-C during run()."""

    def __init__(self, cfg, checkpoint, iterations_in_run):
        from types import SimpleNamespace

        self.cfg, self.progress = cfg, None
        self.problem = SimpleNamespace(total_iterations=3)
        self.checkpoint = SimpleNamespace(path=checkpoint, exists=checkpoint.exists)
        self.iterations_in_run = iterations_in_run

    def load_state(self):
        from types import SimpleNamespace

        return SimpleNamespace(iteration=json.loads(self.checkpoint.path.read_text())["state"]["iteration"])

    def run(self, resume, start=None):
        if self.iterations_in_run:
            atomic_write_text(self.checkpoint.path, json.dumps({"state": {"iteration": self.iterations_in_run}}))
        raise KeyboardInterrupt


def interrupt_optimize(monkeypatch, tmp_path, iterations_in_run, *args):
    """`clflow optimize scene.yaml *args` with the config loading faked and Ctrl-C after
    ``iterations_in_run`` checkpointed iterations (0: before the first finished)."""
    from types import SimpleNamespace

    import clflow.pipeline.fit
    import clflow.scene.config

    cfg = SimpleNamespace(
        optimize=SimpleNamespace(search=None, materials=()),
        output=tmp_path,
        video=tmp_path / "guidance.mp4",
        more_views=(),
        material=SimpleNamespace(type="elastic"),
        objects=(SimpleNamespace(material=SimpleNamespace(type="elastic")),),  # one object
        simulation=SimpleNamespace(frames=8),
    )
    monkeypatch.setattr(clflow.scene.config, "load_config", lambda path, overrides=(): cfg)
    monkeypatch.setattr(clflow.pipeline.fit, "resampled_guidance", lambda cfg, video, frames: None)
    monkeypatch.setattr(
        clflow.pipeline.fit,
        "Optimization",
        lambda cfg, **options: _InterruptedOptimization(cfg, tmp_path / "checkpoint.json", iterations_in_run),
    )
    return CliRunner().invoke(cli, ["optimize", "scene.yaml", *args])


def test_ctrl_c_in_any_command_is_one_line_and_exit_130(monkeypatch):
    @click.command("sleepy")
    def sleepy():
        raise KeyboardInterrupt

    monkeypatch.setitem(cli.commands, "sleepy", sleepy)
    res = CliRunner().invoke(cli, ["sleepy"])
    assert res.exit_code == 130 and res.output == "Error: interrupted\n"


def test_ctrl_c_in_optimize_gives_the_resume_hint_and_exit_130(monkeypatch, tmp_path):
    res = interrupt_optimize(monkeypatch, tmp_path, 2)
    assert res.exit_code == 130, res.output
    assert "interrupted after 2 iterations" in res.output and "--resume" in res.output


def test_the_resume_hint_repeats_the_options_the_run_was_started_with(monkeypatch, tmp_path):
    """Run as printed, it resumes the same run: the same -o, --set, limits (it used to say
    only `clflow optimize CONFIG --resume`, which fails for a run started with -o)."""
    from clflow.pipeline.runs import resume_command

    res = interrupt_optimize(monkeypatch, tmp_path, 2, "--set", "flow.preset=fast", "--set", "a.b=c d")
    assert res.exit_code == 130, res.output
    hint = res.output.split("continue with `")[1].split("`")[0]
    assert hint == "clflow optimize scene.yaml --resume --set flow.preset=fast --set 'a.b=c d'"
    again = resume_command("a b.yaml", "my results", ("x=1",), None, 64, True, {})
    assert (
        again
        == "clflow optimize 'a b.yaml' --resume -o 'my results' --set x=1 --max-substeps 64 --force-video --parallel"
    )


def test_ctrl_c_before_the_first_iteration_says_nothing_was_saved(monkeypatch, tmp_path):
    for earlier_run in (False, True):  # an earlier run's checkpoint.json is not this run's
        if earlier_run:
            atomic_write_text(tmp_path / "checkpoint.json", json.dumps({"state": {"iteration": 7}}))
        res = interrupt_optimize(monkeypatch, tmp_path, 0)
        assert res.exit_code == 130, res.output
        assert "nothing was saved" in res.output and "saved in" not in res.output and "--resume" not in res.output


def test_ctrl_c_right_after_resuming_keeps_the_resume_hint(monkeypatch, tmp_path):
    atomic_write_text(tmp_path / "checkpoint.json", json.dumps({"state": {"iteration": 7}}))
    res = interrupt_optimize(monkeypatch, tmp_path, 0, "--resume")
    assert res.exit_code == 130 and "interrupted after 7 iterations" in res.output and "--resume" in res.output


@pytest.mark.parametrize("flags, folded", [([], True), (["-v"], True), (["-vv"], False)])
def test_pyopencl_build_messages_are_dropped_unless_vv(device, caplog, flags, folded):
    """pyopencl logs a line per program even when the driver's cache answers: every run said
    "compiling kernels". Only a build that takes long says so (the next test), once per program."""
    import logging

    assert CliRunner().invoke(cli, [*flags, "devices"]).exit_code == 0
    caplog.clear()
    for name in ("pyopencl", "pyopencl.cache"):  # whatever level an earlier test left them at
        caplog.set_level(logging.DEBUG, logger=name)
    with caplog.at_level(logging.DEBUG):
        for kernel in ("p2g", "g2p"):  # what pyopencl logs after a slow uncached build
            logging.getLogger("pyopencl").info(
                "build program: kernel '%s' was part of a lengthy %s (%.2f s)", kernel, "uncached source build", 1.5
            )
            logging.getLogger("pyopencl.cache").debug("build program: binary cache miss (key: %s)", kernel)
        logging.getLogger("pyopencl").info("another message")
    lines = [(r.name, r.getMessage()) for r in caplog.records]
    if folded:
        assert lines == [("pyopencl", "another message")]
    else:
        assert len(lines) == 5 and lines[0] == (
            "pyopencl",
            "build program: kernel 'p2g' was part of a lengthy uncached source build (1.50 s)",
        )


def test_only_a_slow_build_says_it_compiled(device, caplog, monkeypatch):
    import logging

    from clflow.runtime import programs

    monkeypatch.setenv("CLFLOW_PROGRAM_CACHE", "off")  # a program of an earlier run would load, not compile
    kernel_defines = {"REDUCE_WG": 64, "ROWS_PER_ITEM": 16}
    device.program("common/reduce.cl", "float", kernel_defines)
    with caplog.at_level(logging.INFO, logger="clflow.runtime"):
        device.program("common/reduce.cl", "float", kernel_defines)  # built: nothing to say
        monkeypatch.setattr(programs, "SLOW_BUILD_SECONDS", -1.0)  # every build counts as slow
        device.program("common/reduce.cl", "float", {**kernel_defines, "PROBE_SLOW": 1})
    said = [r.getMessage() for r in caplog.records if r.name == "clflow.runtime"]
    assert len(said) == 1 and said[0].startswith("compiled kernels_cl/common/reduce.cl in ")


def test_a_broken_plugin_is_listed_and_reports_its_error_when_run(monkeypatch):
    import clflow_cli.main as main

    class BrokenEntryPoint:
        name, value = "sparkle", "clflow_sparkle.cli:sparkle"

        def load(self):
            raise ImportError("No module named 'clflow_sparkle'")

    monkeypatch.setattr(
        main,
        "entry_points",
        lambda group, **select: [ep for ep in [BrokenEntryPoint()] if select.get("name", ep.name) == ep.name],
    )
    listing = CliRunner().invoke(cli, ["--help"])
    assert listing.exit_code == 0 and "sparkle" in listing.output and "broken plugin" in listing.output
    run = CliRunner().invoke(cli, ["sparkle", "--anything"])
    assert run.exit_code == 1
    assert "plugin command 'sparkle' (clflow_sparkle.cli:sparkle) failed to load: ImportError" in run.output
    assert "Traceback" not in run.output


def test_progress_off_a_terminal_is_a_line_per_tenth(capsys):
    from clflow_cli.progress import progress

    with progress(25, "rendering") as advance:
        for k in range(25):
            advance(f"view_{k}")
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "rendering: 2/25 view_1" and lines[-1] == "rendering: 25/25 view_24"
    assert len(lines) == 13  # every 2nd of 25, and the last


def test_progress_jumps_to_a_unit_and_shows_items_its_way(capsys):
    """reconstruct's use: the trainer reports its step (a resumed run starts late), a line
    every 100 steps, items shown by the caller's function."""
    from clflow_cli.progress import progress

    with progress(250, "reconstructing", show=lambda info: f"PSNR {info:.1f} dB", every=100) as advance:
        for step in range(51, 251):
            advance(step / 10, to=step)
    assert capsys.readouterr().err.splitlines() == [
        "reconstructing: 100/250 PSNR 10.0 dB",
        "reconstructing: 200/250 PSNR 20.0 dB",
        "reconstructing: 250/250 PSNR 25.0 dB",
    ]


# command path -> (its output parameter, the other arguments it needs to parse)
OUT_PARAMETERS = {
    ("render",): ("output_dir", ["s.ply"]),
    ("render4d",): ("out_dir", ["sim"]),
    ("simulate",): ("out_dir", []),
    ("flow",): ("output", ["v.mp4"]),
    ("generate",): ("output", ["i.png", "--model", "m"]),
    ("optimize",): ("output", ["c.yaml"]),
    ("eval", "sysid"): ("output", []),
    ("query",): ("output", ["i.png"]),
    ("reconstruct",): ("output_dir", ["images"]),
    ("sweep",): ("output", ["spec.yaml"]),
}


def _command(path: tuple[str, ...]) -> click.Command:
    command = cli
    for name in path:
        command = command.get_command(click.Context(command), name)
    return command


@pytest.mark.parametrize("path", list(OUT_PARAMETERS), ids=" ".join)
def test_output_is_dash_o_or_out_and_the_old_spellings_still_work(path):
    name, args = OUT_PARAMETERS[path]
    command = _command(path)
    help_text = CliRunner().invoke(cli, [*path, "--help"]).output
    assert "-o, --out" in help_text and "--output-dir" not in help_text
    assert "--output " not in help_text and "--output," not in help_text  # the aliases are not shown
    for spelling in ("-o", "--out", "--output", "--output-dir"):
        ctx = command.make_context(" ".join(path), [*args, spelling, "target"])
        assert str(ctx.params[name]) == "target", spelling


def test_simulate_param_and_params_from_are_distinct_and_params_still_works():
    command = _command(("simulate",))
    help_text = CliRunner().invoke(cli, ["simulate", "--help"]).output
    assert "--params-from PARAMS.JSON" in help_text and "--params " not in help_text
    for spelling in ("--params-from", "--params"):
        ctx = command.make_context("simulate", ["c.yaml", spelling, "p.json", "-p", "youngs_modulus=2e4"])
        assert ctx.params["params_file"] == "p.json" and ctx.params["params"] == {"youngs_modulus": 2e4}
    res = CliRunner().invoke(cli, ["simulate", "--params-from", "p.json"])
    assert res.exit_code == 2 and "--params-from needs a scene CONFIG" in res.output


def test_numbers_are_one_word_with_commas_in_every_command():
    from clflow_cli.options import Numbers

    assert Numbers(3).convert("0,1,0", None, None) == (0.0, 1.0, 0.0)
    assert Numbers(3).convert("0 1 0", None, None) == (0.0, 1.0, 0.0)  # quoted with spaces
    with pytest.raises(click.BadParameter, match="write them as one word with commas"):
        Numbers(4, "X0,Y0,X1,Y1").convert("8", None, None)
    with pytest.raises(click.BadParameter, match="expected 3 comma-separated finite numbers, got '1,nan,2'"):
        Numbers(3).convert("1,nan,2", None, None)
    for path, option in (
        (("render",), "--box"),
        (("flow",), "--box"),
        (("query",), "--box"),
        (("render",), "--up"),
        (("simulate",), "--velocity"),
        (("simulate",), "--gravity"),
        (("simulate",), "--center"),
    ):
        param = next(p for p in _command(path).params if option in p.opts)
        assert isinstance(param.type, Numbers), (path, option)
    up = next(p for p in _command(("render",)).params if p.name == "up")
    assert up.type.convert(up.default, up, None) == (0.0, 1.0, 0.0)  # +y, as scene configs (scene.up)


def test_eval_sysid_progress_lines_use_the_pipelines_row_format(monkeypatch, tmp_path):
    import clflow_datasets.sysid as sysid

    def evaluate(names, out, settings, force, progress, run_cases, cases):
        progress("torus", {"iteration": 0, "loss": 1.5, "params": {"youngs_modulus": 2e4}, "seconds": 0.5})
        return {"cases": {}}

    monkeypatch.setattr(sysid, "evaluate", evaluate)
    monkeypatch.setattr(sysid, "markdown", lambda summary: "")
    res = CliRunner().invoke(cli, ["eval", "sysid", "-o", tmp_path, "--case", "torus"])
    assert res.exit_code == 0 and res.output == "torus: iteration 1: loss 1.5  youngs_modulus=2e+04  0.5 s/it\n"


@pytest.mark.slow
def test_sigterm_ends_a_command_as_ctrl_c_does_with_exit_143(tmp_path):
    """SIGTERM (what schedulers, Ray and `kill` send) mid-optimisation: the same one line as
    Ctrl-C, exit status 143, no temporary file left in the output folder, the user's own
    file there byte for byte as it was."""
    import hashlib
    import signal

    folder = tmp_path / "demo"
    folder.mkdir()
    notes = folder / "notes.txt"
    notes.write_bytes(b"my notes\n" * 100)
    digest = hashlib.sha256(notes.read_bytes()).hexdigest()
    proc = subprocess.Popen(
        [sys.executable, "-m", "clflow_cli", "demo", "--quick", str(folder)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    seen = []
    for line in proc.stdout:  # progress lines until the optimisation runs
        seen.append(line)
        if line.startswith("iteration 2/"):
            break
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=300)
    output = "".join(seen) + rest
    assert proc.returncode == 143, output[-3000:]
    errors = [line for line in output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and "Traceback" not in output, output[-3000:]
    assert not [p for p in folder.rglob("*") if ".tmp" in p.name], sorted(folder.rglob("*"))
    assert hashlib.sha256(notes.read_bytes()).hexdigest() == digest
