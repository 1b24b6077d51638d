"""One run of a sweep, anywhere: in this process with its log and time limit, one after
another, or as Ray tasks with the serial path's sum order."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Iterator

from clflow.errors import ClflowError, InputError
from clflow.fileio.reading import parse_json
from clflow.parallel import ray_session, remote_task, serial_order, task_env
from clflow.sweep.spec import Run, sysid_settings


class RunTimeout(BaseException):
    """A serial run went past its time limit (a BaseException: no ``except Exception`` eats it)."""


def execute(run: Run, folder: str, env: dict[str, str] | None = None, inputs: dict | None = None) -> dict:
    """Run ``run`` in this process with its outputs in ``folder`` and its output lines in
    ``folder/run.log``; returns its record (status ok or failed, with the reason).
    ``inputs`` (clflow.sweep.spec.inputs_of) go to ``folder/inputs.json`` first: a run whose
    folder was last started with other inputs starts over (an optimisation does not resume)."""
    folder_path = Path(folder)
    folder_path.mkdir(parents=True, exist_ok=True)
    fresh = inputs is not None and _started_with(folder_path, inputs)
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
            record.update(status="ok", reason=None, result=_COMMANDS[run.command](run, folder_path, fresh))
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


def _started_with(folder: Path, inputs: dict) -> bool:
    """Whether ``folder``'s last start had other inputs than ``inputs`` (then its outputs are
    not to be continued), and ``inputs`` noted as its latest start's. A folder with a record
    and no inputs.json is an earlier clflow's: other inputs."""
    from clflow.fileio import atomic_write_text

    noted = folder / "inputs.json"
    try:
        other = parse_json(noted.read_text()) != inputs
    except (OSError, ValueError):
        other = (folder / "result.json").exists()
    atomic_write_text(noted, json.dumps(inputs, indent=2))
    return other


def _reason(exc: BaseException) -> str:
    import click

    text = exc.format_message() if isinstance(exc, click.ClickException) else str(exc)
    text = " ".join(text.split())
    return text if isinstance(exc, (ClflowError, click.ClickException)) else f"{type(exc).__name__}: {text}"


def _run_simulate(run: Run, folder: Path, fresh: bool) -> dict:
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


def _run_optimize(run: Run, folder: Path, fresh: bool) -> dict:
    from clflow.pipeline.runs import run_optimization

    results = folder / "results"
    # an interrupted or timed-out try of the same inputs continues; of other inputs, starts over
    resume = not fresh and (results / "checkpoint.json").exists()
    return run_optimization(
        run.config,
        resume,
        run.options.get("iterations"),
        results,
        run.overrides,
        echo=print,
        note=lambda line: print(line, file=sys.stderr),
    )


def _run_sysid(run: Run, folder: Path, fresh: bool) -> dict:  # its inputs are its parameters (its folder)
    from clflow_datasets.sysid import run_case

    record = run_case(run.case, folder / "case", sysid_settings(run.sysid or {}))
    if record.get("status") != "ok":
        raise InputError(str(record.get("status")).removeprefix("failed: "))
    return record


_COMMANDS: dict[str, Callable[[Run, Path, bool], dict]] = {
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


def run_serial(
    runs: list[Run],
    folder_of: Callable[[Run], Path],
    timeout: float | None,
    on_done: Callable[[dict], None],
    env: dict[str, str] | None = None,
    inputs: dict[str, dict] | None = None,
) -> None:
    """Run one after another in this process (a run's ``timeout`` enforced with SIGALRM;
    ``inputs``: each run's by name, for :func:`execute`)."""
    for run in runs:
        limit = run.timeout or timeout
        start = time.perf_counter()
        try:
            with _deadline(limit):
                record = execute(run, str(folder_of(run)), env, (inputs or {}).get(run.name))
        except RunTimeout:
            record = _timed_out(run, limit, time.perf_counter() - start)
        on_done(record)


def _ray_task(run: Run, folder: str, inputs: dict | None = None) -> dict:
    return execute(run, folder, inputs=inputs)  # the env came with the task's runtime_env, before OpenCL started


#: how long a sweep waits for a node that can run its tasks when none is left (a node died)
NO_ROOM_GRACE_S = 10.0


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
    once as the cluster has room for (its nodes now: fewer when one dies), so a run's time
    limit counts from its start. A task that raises is recorded by :func:`execute`; one killed
    (its worker or node died) or past its limit (its worker is killed) is recorded here; the
    others go on. When no node is left that can run a task (for NO_ROOM_GRACE_S), the runs
    not finished are recorded as failed. Ctrl-C cancels the running tasks."""
    import ray

    remote, room = remote_task(task, env, cpus_per_task, resources)
    waiting = list(runs)
    running: dict[Any, tuple[Run, float]] = {}
    no_room_since = None
    try:
        while waiting or running:
            slots = room()
            now = time.perf_counter()
            no_room_since = (no_room_since or now) if slots == 0 else None
            if no_room_since is not None and now - no_room_since > NO_ROOM_GRACE_S:
                _no_room(waiting, running, now, on_done)
                break
            while waiting and (slots is None or len(running) < slots):
                run = waiting.pop(0)
                ref = remote.remote(run, str(folder_of(run))) if args is None else remote.remote(*args(run))
                running[ref] = (run, time.perf_counter())
            deadlines = [start + (r.timeout or timeout) for r, start in running.values() if r.timeout or timeout]
            wait = max(0.05, min([d - now for d in deadlines] + [1.0]))
            if not running:  # no room for one yet
                time.sleep(wait)
                continue
            ready, _ = ray.wait(list(running), num_returns=1, timeout=wait)
            for ref in ready:
                run, start = running.pop(ref)
                on_done(_result(ref, run, start))
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


def _result(ref, run: Run, start: float) -> dict:
    """The record of a finished task: its own, or failed or killed with Ray's reason."""
    import ray

    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:  # raised past execute() (a task without it)
        cause = exc.cause if exc.cause is not None else exc
        return _ended(run, "failed", _reason(cause), time.perf_counter() - start)
    except ray.exceptions.RayError as exc:  # the worker died (killed, out of memory, its node lost)
        cause = " ".join(str(exc).split())[:300]
        return _ended(run, "killed", f"{type(exc).__name__}: {cause}", time.perf_counter() - start)


def _no_room(waiting: list[Run], running: dict, now: float, on_done: Callable[[dict], None]) -> None:
    """Record the runs not finished as failed: no node of the cluster can run them any more."""
    import ray

    reason = f"no node of the Ray cluster can run its task any more (for {NO_ROOM_GRACE_S:g} s; a node left)"
    for ref, (run, start) in list(running.items()):
        with contextlib.suppress(Exception):
            ray.cancel(ref, force=True)
        del running[ref]
        on_done(_ended(run, "failed", reason, now - start))
    for run in waiting:
        on_done(_ended(run, "failed", reason, 0.0))
    waiting.clear()


def _sysid_task(name: str, folder: str, settings, case) -> dict:
    from clflow_datasets import sysid

    return sysid.run_case(name, Path(folder), settings, case=case)  # the driver's definition of the case


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

    def run_cases(names: list[str], out: Path, settings, done: Callable[[str, dict], None], cases: dict) -> None:
        if not names:
            return
        runs = [Run("sysid", case=n, sysid={}, label=n) for n in names]

        def finished(record: dict) -> None:
            name = record["case"]
            if record.get("status") in ("failed", "killed", "timeout"):  # recorded by run_on_ray, not run_case
                record = {
                    "case": name,
                    "material": cases[name].material,
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
                args=lambda run: (run.case, str((out / "cases" / run.case).resolve()), settings, cases[run.case]),
            )

    return run_cases
