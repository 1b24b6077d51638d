"""Many runs at once: ``clflow sweep SPEC -o DIR`` (docs/sweep.md).

A SPEC (YAML) names runs of ``simulate``, ``optimize`` or an ``eval sysid`` case: scene
configs as they are, a base config with a grid or a list of overrides (the ``--set`` keys),
sysid cases, or explicit ``runs``. :func:`load_spec` validates all of it (every run's config
is loaded with its overrides) before any work. Each run gets its own folder,
``DIR/runs/NAME``, NAME stable from the run's parameters; its record (status, reason,
seconds, result) goes to ``NAME/result.json`` and into ``DIR/sweep.json`` and ``sweep.md``,
rewritten atomically as runs finish.

Runs execute as Ray tasks (:func:`run_on_ray`: an embedded local Ray by default, or a
cluster) or one after another in this process (:func:`run_serial`). Each Ray task gets
``cpus_per_task`` CPUs and its OpenCL CPU driver as many threads (``POCL_MAX_PTHREAD_COUNT``),
so tasks do not oversubscribe the cores; ``CLFLOW_P2G_COPIES`` and ``OMP_NUM_THREADS`` are the
driver's (:func:`serial_order`) so a task gives the bits the serial path gives.

    spec = load_spec("sweep.yaml")
    summary = sweep(spec, Path("out"), serial=True)       # or serial=False: Ray
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import logging
import os
import re
import signal
import socket
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from clflow.errors import ClflowError, InputError
from clflow.parallel import ray_session, remote_task, serial_order, task_env

log = logging.getLogger(__name__)

COMMANDS = ("simulate", "optimize", "sysid")
SPEC_KEYS = ("command", "options", "set", "configs", "base", "grid", "overrides", "cases", "sysid", "runs", "timeout")
RUN_KEYS = ("name", "command", "config", "set", "options", "case", "timeout")
#: options of each command (as in its CLI), with a check of the value
OPTIONS: dict[str, dict[str, str]] = {
    "simulate": {"preview": "one of mp4, png, none", "params": "a params.json file", "max_output_gb": "a number > 0"},
    "optimize": {"iterations": "a whole number >= 1"},
    "sysid": {},
}
SYSID_KEYS = ("quick", "iterations", "truth_scale", "noise", "codec", "seed", "views")
FINISHED = ("ok", "failed", "timeout", "killed")  # statuses a run ends with


@dataclass(frozen=True)
class Run:
    """One run of a sweep: a command with its config (absolute path) and overrides, or a sysid case."""

    command: str
    config: str | None = None
    overrides: tuple[str, ...] = ()  # "key.sub=value" (value as JSON, which YAML reads)
    options: dict = field(default_factory=dict, hash=False)
    case: str | None = None
    sysid: dict | None = field(default=None, hash=False)  # sysid settings
    timeout: float | None = None  # seconds; None: the sweep's --timeout
    label: str | None = None  # the spec's name for it

    def params(self) -> dict:
        """What the run depends on (JSON data; the folder name's hash is made from it)."""
        out: dict[str, Any] = {"command": self.command}
        if self.config is not None:
            out["config"] = self.config
        if self.overrides:
            out["set"] = list(self.overrides)
        if self.options:
            out["options"] = dict(sorted(self.options.items()))
        if self.case is not None:
            out.update(case=self.case, sysid=self.sysid)
        return out

    @property
    def name(self) -> str:
        """A stable folder name: readable parts of the parameters and a hash of all of them."""
        digest = hashlib.sha256(json.dumps(self.params(), sort_keys=True).encode()).hexdigest()[:8]
        parts = [self.command, self.label or self.case or Path(self.config or "run").stem]
        slug = re.sub(r"[^A-Za-z0-9._=+-]+", "_", "-".join(parts)).strip("_")[:80]
        return f"{slug}-{digest}"


@dataclass(frozen=True)
class Spec:
    source: Path
    runs: tuple[Run, ...]


# ---------------------------------------------------------------------------------- the spec


def load_spec(path: str | os.PathLike) -> Spec:
    """Read and fully validate a sweep SPEC; any problem is one InputError line."""
    from clflow.fileio import read_text
    from clflow.scene.config.files import DuplicateKeyError, read_yaml

    path = Path(path)
    text = read_text(path, "sweep spec")
    import yaml

    try:
        data = read_yaml(text)
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    except DuplicateKeyError as exc:
        raise InputError(f"{path}: {exc}: duplicate key (each key may appear only once)") from None
    return parse_spec(data, path)


def parse_spec(data: Any, path: Path) -> Spec:
    """Validate parsed SPEC ``data`` (from file ``path``; relative paths are from its folder)."""

    def fail(where: str, what: str) -> InputError:
        return InputError(f"{path}: {where + ': ' if where else ''}{what}")

    def mapping(value: Any, where: str, keys: Iterable[str] | None = None) -> dict:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise fail(where, f"must be a mapping, got {value!r}")
        if keys is not None:
            unknown = [k for k in value if k not in keys]
            if unknown:
                raise fail(where, f"unknown key {unknown[0]!r}; the keys are {', '.join(keys)}")
        return value

    def items(value: Any, where: str) -> list:
        if value is None:
            return []
        if not isinstance(value, list):
            raise fail(where, f"must be a list, got {value!r}")
        return value

    def command_of(value: Any, where: str) -> str:
        if value not in COMMANDS:
            raise fail(where, f"unknown command {value!r}; the commands are {', '.join(COMMANDS)}")
        return value

    def config_path(value: Any, where: str) -> str:
        if not isinstance(value, str) or not value:
            raise fail(where, f"must be a config file path, got {value!r}")
        file = (path.parent / value).resolve()
        if not file.is_file():
            raise fail(where, f"config {value} not found (paths are relative to the spec's folder)")
        return str(file)

    def overrides(value: Any, where: str) -> tuple[str, ...]:
        out = []
        for key, v in mapping(value, where).items():
            if not isinstance(key, str) or not re.fullmatch(r"[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*", key):
                raise fail(where, f"{key!r} is not a dotted config key (e.g. simulation.frames)")
            out.append(f"{key}={json.dumps(v)}")
        return tuple(out)

    def options(command: str, value: Any, where: str) -> dict:
        given = mapping(value, where, OPTIONS[command])
        for key, v in given.items():
            ok = {
                "preview": lambda: v in ("mp4", "png", "none"),
                "params": lambda: isinstance(v, str) and (path.parent / v).is_file(),
                "max_output_gb": lambda: isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0,
                "iterations": lambda: isinstance(v, int) and not isinstance(v, bool) and v >= 1,
            }[key]()
            if not ok:
                raise fail(f"{where}.{key}", f"must be {OPTIONS[command][key]}, got {v!r}")
        if "params" in given:
            given = {**given, "params": str((path.parent / given["params"]).resolve())}
        return dict(given)

    def seconds(value: Any, where: str) -> float | None:
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise fail(where, f"must be a number of seconds > 0, got {value!r}")
        return float(value)

    top = mapping(data, "", SPEC_KEYS)
    if not top:
        raise fail("", "the spec is empty; it needs configs, base with grid or overrides, cases or runs")
    command = command_of(top.get("command", "optimize"), "command")
    common_set = overrides(top.get("set"), "set")
    common_options = options(command, top.get("options"), "options")
    timeout = seconds(top.get("timeout"), "timeout")
    sysid = _sysid_settings(mapping(top.get("sysid"), "sysid", SYSID_KEYS), fail)
    runs: list[Run] = []

    def config_run(
        config: str,
        sets: tuple[str, ...],
        cmd: str = command,
        opts: dict | None = None,
        limit: float | None = timeout,
        label: str | None = None,
        where: str = "",
    ) -> None:
        if cmd == "sysid":
            raise fail(where, "a sysid run takes a case, not a config")
        if label is None:  # readable: the config's name and what this run sets besides the spec's set
            label = "-".join(
                [Path(config).stem] + [f"{o.split('=')[0].split('.')[-1]}={o.partition('=')[2]}" for o in sets]
            )
        runs.append(
            Run(cmd, config, common_set + sets, common_options if opts is None else opts, timeout=limit, label=label)
        )

    for i, config in enumerate(items(top.get("configs"), "configs")):
        config_run(config_path(config, f"configs[{i}]"), (), where=f"configs[{i}]")
    grid = mapping(top.get("grid"), "grid")
    listed = items(top.get("overrides"), "overrides")
    if "base" in top:
        base = config_path(top["base"], "base")
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise fail(f"grid.{key}", f"must be a non-empty list of values, got {values!r}")
        keys = list(grid)
        combos = [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))] if grid else []
        combos += [mapping(o, f"overrides[{i}]") for i, o in enumerate(listed)]
        for combo in combos or [{}]:
            config_run(base, overrides(combo, "grid"), where="base")
    elif grid or listed:
        raise fail("grid" if grid else "overrides", "needs a base config (base: FILE)")
    cases = items(top.get("cases"), "cases")
    if cases and command != "sysid":
        raise fail("cases", f"sysid cases need command: sysid, not {command}")
    for case in cases:
        runs.append(Run("sysid", case=_case(case, "cases", fail), sysid=sysid, timeout=timeout))
    for i, entry in enumerate(items(top.get("runs"), "runs")):
        where = f"runs[{i}]"
        entry = mapping(entry, where, RUN_KEYS)
        cmd = command_of(entry.get("command", command), f"{where}.command")
        label = entry.get("name")
        if label is not None and (not isinstance(label, str) or not re.fullmatch(r"[A-Za-z0-9._=+-]+", label)):
            raise fail(f"{where}.name", f"must be letters, digits and . _ = + -, got {label!r}")
        limit = seconds(entry.get("timeout"), f"{where}.timeout") or timeout
        opts = {**(common_options if cmd == command else {}), **options(cmd, entry.get("options"), f"{where}.options")}
        if cmd == "sysid":
            if "config" in entry or "set" in entry:
                raise fail(where, "a sysid run takes a case, not a config or set")
            runs.append(
                Run(
                    "sysid",
                    case=_case(entry.get("case"), f"{where}.case", fail),
                    sysid=sysid,
                    timeout=limit,
                    label=label,
                )
            )
        else:
            if "case" in entry:
                raise fail(f"{where}.case", f"only sysid runs take a case, this one is {cmd}")
            if "config" not in entry:
                raise fail(where, f"a {cmd} run needs a config")
            config_run(
                config_path(entry["config"], f"{where}.config"),
                overrides(entry.get("set"), f"{where}.set"),
                cmd,
                opts,
                limit,
                label,
                where,
            )
    if not runs:
        raise fail("", "no runs: give configs, base (with grid or overrides), cases or runs")
    keys = [json.dumps(r.params(), sort_keys=True) for r in runs]
    twice = sorted({r.name for r, k in zip(runs, keys) if keys.count(k) > 1})
    if twice:
        raise fail("", f"runs given twice (same command, config and overrides): {', '.join(twice)}")
    for run in runs:  # every config as it will run: unknown keys, bad values, missing files
        if run.config is not None:
            from clflow.scene.config import load_config

            try:
                load_config(run.config, run.overrides)
            except InputError as exc:
                raise fail(f"run {run.name}", str(exc)) from None
    return Spec(path, tuple(runs))


def _case(value: Any, where: str, fail: Callable[[str, str], InputError]) -> str:
    from clflow_datasets.sysid import CASES

    if value not in CASES:
        raise fail(where, f"unknown sysid case {value!r}; the cases are {', '.join(CASES)}")
    return value


def _sysid_settings(given: dict, fail: Callable[[str, str], InputError]) -> dict:
    """The ``sysid`` section as JSON data (checked when a run makes its Settings)."""
    checks = {
        "quick": lambda v: isinstance(v, bool),
        "iterations": lambda v: _whole(v, 1),
        "truth_scale": lambda v: _whole(v, 1),
        "seed": lambda v: _whole(v, None),
        "views": lambda v: _whole(v, 1) and v <= 4,
        "codec": lambda v: v in (None, ".mp4", ".webm", ".avi"),
        "noise": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0,
    }
    for key, value in given.items():
        if not checks[key](value):
            raise fail(f"sysid.{key}", f"bad value {value!r}")
    return dict(sorted(given.items()))


def _whole(v: Any, low: int | None) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and (low is None or v >= low)


def sysid_settings(record: dict):
    """clflow_datasets.sysid.Settings from a spec's ``sysid`` section."""
    import dataclasses

    from clflow_datasets.sysid import FULL, QUICK, Settings

    resolution = QUICK if record.get("quick") else FULL
    if record.get("iterations") is not None:
        resolution = dataclasses.replace(resolution, iterations=record["iterations"])
    return Settings(resolution=resolution, **{k: v for k, v in record.items() if k not in ("quick", "iterations")})


# ------------------------------------------------------------------------- one run, anywhere


class RunTimeout(BaseException):
    """A serial run went past its time limit (a BaseException: no ``except Exception`` eats it)."""


def execute(run: Run, folder: str, env: dict[str, str] | None = None) -> dict:
    """Run ``run`` in this process with its outputs in ``folder`` and its output lines in
    ``folder/run.log``; returns its record (status ok or failed, with the reason)."""
    folder_path = Path(folder)
    folder_path.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {"name": run.name, **run.params(), "host": socket.gethostname()}
    start = time.perf_counter()
    saved = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    root = logging.getLogger()
    with open(folder_path / "run.log", "a") as out, contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        handler = logging.StreamHandler(out)
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        handlers, root.handlers = root.handlers, [handler]  # the run's log lines go to its run.log only
        level = root.level
        root.setLevel(min(level, logging.INFO) if level else logging.INFO)
        try:
            record.update(status="ok", reason=None, result=_COMMANDS[run.command](run, folder_path))
        except RunTimeout:
            raise
        except Exception as exc:  # recorded, and the sweep goes on
            traceback.print_exc(file=out)
            record.update(status="failed", reason=_reason(exc), result=None)
        finally:
            root.handlers = handlers
            root.setLevel(level)
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
    record["seconds"] = round(time.perf_counter() - start, 3)
    return record


def _reason(exc: BaseException) -> str:
    import click

    text = exc.format_message() if isinstance(exc, click.ClickException) else str(exc)
    text = " ".join(text.split())
    return text if isinstance(exc, (ClflowError, click.ClickException)) else f"{type(exc).__name__}: {text}"


def _run_simulate(run: Run, folder: Path) -> dict:
    from clflow.limits import DEFAULT_MAX_OUTPUT_GB
    from clflow.pipeline.runs import simulate_scene

    o = run.options
    simulate_scene(
        run.config,
        o.get("params"),
        folder / "simulation",
        o.get("preview", "mp4"),
        o.get("max_output_gb", DEFAULT_MAX_OUTPUT_GB),
        run.overrides,
        echo=print,
    )
    import numpy as np

    with np.load(folder / "simulation" / "gaussians.npz") as g:
        moving, frames = g["object_means"].shape[1], g["object_means"].shape[0]
    return {"gaussians": moving, "frames": frames, "output": "simulation/"}


def _run_optimize(run: Run, folder: Path) -> dict:
    from clflow.pipeline.runs import run_optimization

    results = folder / "results"
    resume = (results / "checkpoint.json").exists()  # an interrupted or timed-out try continues
    return run_optimization(
        run.config,
        resume,
        run.options.get("iterations"),
        results,
        run.overrides,
        echo=print,
        note=lambda line: print(line, file=sys.stderr),
    )


def _run_sysid(run: Run, folder: Path) -> dict:
    from clflow_datasets.sysid import run_case

    record = run_case(run.case, folder / "case", sysid_settings(run.sysid or {}))
    if record.get("status") != "ok":
        raise InputError(str(record.get("status")).removeprefix("failed: "))
    return record


_COMMANDS: dict[str, Callable[[Run, Path], dict]] = {
    "simulate": _run_simulate,
    "optimize": _run_optimize,
    "sysid": _run_sysid,
}


@contextlib.contextmanager
def _deadline(seconds: float | None) -> Iterator[None]:
    """Raise RunTimeout in this (main) thread after ``seconds``; no limit elsewhere."""
    import threading

    if not seconds or threading.current_thread() is not threading.main_thread():
        yield
        return

    def expired(signum, frame):
        raise RunTimeout()

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _ended(run: Run, status: str, reason: str, seconds: float) -> dict:
    """The record of a run that ended without a result (failed, killed, timeout)."""
    return {
        "name": run.name,
        **run.params(),
        "status": status,
        "reason": reason,
        "result": None,
        "seconds": round(seconds, 3),
    }


def _timed_out(run: Run, limit: float, seconds: float) -> dict:
    return _ended(run, "timeout", f"exceeded the time limit of {limit:g} s", seconds)


# -------------------------------------------------------------------------------- executors


def run_serial(
    runs: list[Run],
    folder_of: Callable[[Run], Path],
    timeout: float | None,
    on_done: Callable[[dict], None],
    env: dict[str, str] | None = None,
) -> None:
    """Run one after another in this process (a run's ``timeout`` enforced with SIGALRM)."""
    for run in runs:
        limit = run.timeout or timeout
        start = time.perf_counter()
        try:
            with _deadline(limit):
                record = execute(run, str(folder_of(run)), env)
        except RunTimeout:
            record = _timed_out(run, limit, time.perf_counter() - start)
        on_done(record)


def _ray_task(run: Run, folder: str) -> dict:
    return execute(run, folder)  # the env came with the task's runtime_env, before OpenCL started


def run_on_ray(
    runs: list[Run],
    folder_of: Callable[[Run], Path],
    timeout: float | None,
    on_done: Callable[[dict], None],
    *,
    env: dict[str, str],
    cpus_per_task: int = 1,
    resources: dict[str, float] | None = None,
    task: Callable = _ray_task,
    args: Callable[[Run], tuple] | None = None,
) -> None:
    """Run each run as a Ray task (Ray already started: :func:`start_ray`), at most as many at
    once as the cluster has room for, so a run's time limit counts from its start. A task that
    raises is recorded by :func:`execute`; one killed (worker died) or past its limit (its
    worker is killed) is recorded here; the others go on. Ctrl-C cancels the running tasks."""
    import ray

    remote, room = remote_task(task, env, cpus_per_task, resources)
    slots = (len(runs) if room is None else room) or 1
    waiting = list(runs)
    running: dict[Any, tuple[Run, float]] = {}
    try:
        while waiting or running:
            while waiting and len(running) < slots:
                run = waiting.pop(0)
                ref = remote.remote(run, str(folder_of(run))) if args is None else remote.remote(*args(run))
                running[ref] = (run, time.perf_counter())
            now = time.perf_counter()
            deadlines = [start + (r.timeout or timeout) for r, start in running.values() if r.timeout or timeout]
            wait = max(0.05, min([d - now for d in deadlines] + [1.0]))
            ready, _ = ray.wait(list(running), num_returns=1, timeout=wait)
            for ref in ready:
                run, start = running.pop(ref)
                try:
                    record = ray.get(ref)
                except ray.exceptions.RayTaskError as exc:  # raised past execute() (a task without it)
                    cause = exc.cause if exc.cause is not None else exc
                    record = _ended(run, "failed", _reason(cause), time.perf_counter() - start)
                except ray.exceptions.RayError as exc:  # the worker died (killed, out of memory, node lost)
                    cause = " ".join(str(exc).split())[:300]
                    record = _ended(run, "killed", f"{type(exc).__name__}: {cause}", time.perf_counter() - start)
                on_done(record)
            now = time.perf_counter()
            for ref, (run, start) in list(running.items()):
                limit = run.timeout or timeout
                if limit and now - start > limit:
                    ray.cancel(ref, force=True)  # kills its worker process
                    del running[ref]
                    on_done(_timed_out(run, limit, now - start))
    except BaseException:
        for ref in running:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        raise


def _sysid_task(name: str, folder: str, settings, case) -> dict:
    from clflow_datasets import sysid

    sysid.CASES[name] = case  # the driver's definition of the case, whatever this worker's copy says
    return sysid.run_case(name, Path(folder), settings)


def sysid_on_ray(
    *,
    address: str | None = None,
    cpus_per_task: int = 1,
    resources: dict[str, float] | None = None,
    device: str | None = None,
    timeout: float | None = None,
    echo: Callable[[str], None] = lambda line: None,
) -> Callable:
    """A ``run_cases`` for clflow_datasets.sysid.evaluate (``clflow eval sysid --parallel``):
    each case a Ray task with the serial path's P2G sum order, so the records match it."""

    def run_cases(names: list[str], out: Path, settings, done: Callable[[str, dict], None]) -> None:
        from clflow_datasets.sysid import CASES

        if not names:
            return
        runs = [Run("sysid", case=n, sysid={}, label=n) for n in names]

        def finished(record: dict) -> None:
            name = record["case"]
            if record.get("status") in ("failed", "killed", "timeout"):  # recorded by run_on_ray, not run_case
                record = {
                    "case": name,
                    "material": CASES[name].material,
                    "seconds": record["seconds"],
                    "status": f"failed: {record['status']}: {record['reason']}",
                }
            echo(f"{name}: {record['status']} ({record.get('seconds', 0):.0f} s)")
            done(name, record)

        with ray_session(address):
            run_on_ray(
                runs,
                lambda run: out / "cases" / run.case,
                timeout,
                finished,
                env=task_env(cpus_per_task, device, serial_order()),
                cpus_per_task=cpus_per_task,
                resources=resources,
                task=_sysid_task,
                args=lambda run: (run.case, str((out / "cases" / run.case).resolve()), settings, CASES[run.case]),
            )

    return run_cases


# ------------------------------------------------------------------------------- the sweep


def previous_record(folder: Path) -> dict | None:
    try:
        record = json.loads((folder / "result.json").read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("status") in FINISHED else None


def sweep(
    spec: Spec,
    out: Path,
    *,
    serial: bool = False,
    address: str | None = None,
    cpus_per_task: int = 1,
    resources: dict[str, float] | None = None,
    timeout: float | None = None,
    retry_failed: bool = False,
    device: str | None = None,
    echo: Callable[[str], None] = lambda line: None,
) -> dict:
    """Run the spec's runs into ``out`` (skipping those finished earlier: all but failed ones
    with ``retry_failed``), writing ``sweep.json`` and ``sweep.md`` as they finish; returns
    the summary. KeyboardInterrupt leaves the finished runs recorded."""
    from clflow.fileio import atomic_write_text
    from clflow.limits import check_output

    out = Path(out).resolve()  # tasks run in other working folders
    check_output(out)
    runs_dir = out / "runs"

    def folder_of(run: Run) -> Path:
        return runs_dir / run.name

    summary: dict[str, Any] = {"spec": str(spec.source.resolve()), "runs": {}}
    todo = []
    for run in spec.runs:
        earlier = previous_record(folder_of(run))
        if earlier and (earlier["status"] == "ok" or not retry_failed):
            summary["runs"][run.name] = {**earlier, "skipped": True}
        else:
            summary["runs"][run.name] = {"name": run.name, **run.params(), "status": "pending"}
            todo.append(run)

    def write() -> None:
        summary["finished"] = sum(r["status"] in FINISHED for r in summary["runs"].values())
        atomic_write_text(out / "sweep.json", json.dumps(summary, indent=2))
        atomic_write_text(out / "sweep.md", markdown(summary))

    def done(record: dict) -> None:
        record["date"] = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        atomic_write_text(runs_dir / record["name"] / "result.json", json.dumps(record, indent=2))
        summary["runs"][record["name"]] = record
        write()
        echo(
            f"{record['name']}: {record['status']}{': ' + record['reason'] if record.get('reason') else ''} "
            f"({record['seconds']:.1f} s)"
        )

    out.mkdir(parents=True, exist_ok=True)
    write()
    skipped = len(spec.runs) - len(todo)
    if skipped:
        echo(
            f"{skipped} run(s) finished earlier, skipped"
            + ("" if retry_failed else " (--retry-failed reruns the failed ones)")
        )
    if not todo:
        return summary
    order = serial_order()
    summary["mode"] = "serial" if serial else f"ray ({address or 'local'}, {cpus_per_task} CPU per task)"
    try:
        if serial:
            run_serial(todo, folder_of, timeout, done, env=order)  # (torch's threads are this process's already)
        else:
            with ray_session(address, instead=None):
                run_on_ray(
                    todo,
                    folder_of,
                    timeout,
                    done,
                    env=task_env(cpus_per_task, device, order),
                    cpus_per_task=cpus_per_task,
                    resources=resources,
                )
    finally:
        write()
    return summary


def markdown(summary: dict) -> str:
    """The summary as a Markdown table, one row per run."""
    runs = summary["runs"].values()
    counts = {s: sum(r["status"] == s for r in runs) for s in ("ok", "failed", "timeout", "killed", "pending")}
    lines = [
        f"# Sweep of {summary['spec']}",
        "",
        ", ".join(f"{n} {s}" for s, n in counts.items() if n) + f" of {len(summary['runs'])} runs",
        "",
        "| run | command | config / case | set | status | seconds | result or reason |",
        "|---" * 7 + "|",
    ]
    for r in runs:
        what = r.get("case") or Path(r.get("config", "")).name
        sets = "<br>".join(r.get("set", []))
        if r["status"] == "ok":
            result = r.get("result") or {}
            detail = ", ".join(
                f"{k} {_short(v)}"
                for k, v in result.items()
                if isinstance(v, (int, float, str)) and not isinstance(v, bool)
            )[:200]
        else:
            detail = (r.get("reason") or "").replace("|", "\\|")
        seconds = f"{r['seconds']:.1f}" if isinstance(r.get("seconds"), (int, float)) else "-"
        lines.append(f"| {r['name']} | {r['command']} | {what} | {sets} | {r['status']} | {seconds} | {detail} |")
    return "\n".join(lines) + "\n"


def _short(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


__all__ = [
    "COMMANDS",
    "Run",
    "Spec",
    "execute",
    "load_spec",
    "markdown",
    "parse_spec",
    "run_on_ray",
    "run_serial",
    "sweep",
]
