"""Runs as Ray tasks (the optional extra ``clflow[sweep]``): starting or joining Ray, one
session for a run's task maps, a task's environment that keeps the serial path's bits, and
mapping a function over tasks. clflow.sweep runs sweep specs with it, clflow.pipeline the
search starts' polishes and the material hypotheses of ``clflow optimize --parallel``.
"""

from __future__ import annotations

import contextlib
import logging
import os
from typing import Any, Callable, Iterator

from clflow.errors import ClflowError, InputError

OBJECT_STORE_BYTES = 80 * 1024**2  # the embedded Ray's object store: tasks return small records only


def task_env(cpus_per_task: int, device: str | None, order: dict[str, str]) -> dict[str, str]:
    """Environment of each task: its OpenCL CPU driver limited to its CPUs, the device chosen
    by the driver, and ``order`` (:func:`serial_order`: the serial path's last bits)."""
    threads = str(cpus_per_task)
    env = {
        "POCL_MAX_PTHREAD_COUNT": threads,  # PoCL <= 4 (pthread driver)
        "POCL_CPU_MAX_CU_COUNT": threads,  # PoCL >= 5
        "OMP_WAIT_POLICY": "PASSIVE",
        **order,
    }
    if device:
        env["CLFLOW_DEVICE"] = device
    return env


def serial_order() -> dict[str, str]:
    """What sets a run's last bits in this process besides its inputs: the MPM's P2G grid
    copies (follows PoCL's threads unless fixed) and torch's threads (its reductions split
    their sums by thread). A task given these gives the serial path's bits whatever its own
    thread count; torch's threads sleep between its (short) ops, OMP_WAIT_POLICY=PASSIVE."""
    import torch

    from clflow.mpm.substep import GRID_COPIES_ENV, wanted_grid_copies
    from clflow.runtime import get_device

    return {GRID_COPIES_ENV: str(wanted_grid_copies(get_device())), "OMP_NUM_THREADS": str(torch.get_num_threads())}


def ray_missing(instead: str = "run the same spec in this process with --serial") -> str:
    return f"Ray is not installed: pip install 'clflow[sweep]' (or {instead})"


def require_ray(instead: str | None = None) -> None:
    """InputError (what to install, or ``instead``) when Ray cannot be imported."""
    try:
        import ray  # noqa: F401
    except ImportError:
        raise InputError(ray_missing(*([instead] if instead else []))) from None


def start_ray(address: str | None, cpus: int | None = None, instead: str | None = None):
    """Join the cluster at ``address`` (``ray://host:port`` or ``auto``), or start an embedded
    local Ray with this machine's cores, no dashboard and a small object store. Returns
    True when it started one (so the caller shuts it down)."""
    require_ray(instead)
    import ray

    if ray.is_initialized():
        return False
    quiet = {"log_to_driver": False, "configure_logging": True, "logging_level": logging.WARNING}
    try:
        if address:
            ray.init(address=address, **quiet)
        else:
            ray.init(
                num_cpus=cpus or os.cpu_count() or 1,
                include_dashboard=False,
                object_store_memory=OBJECT_STORE_BYTES,
                **quiet,
            )
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise InputError(
            f"cannot start Ray{' at ' + address if address else ''}: {' '.join(str(exc).split())}"
        ) from None
    return True


def remote_task(task: Callable, env: dict[str, str], cpus_per_task: int, resources: dict[str, float] | None):
    """``task`` as a Ray remote function of ``resources`` (CPU and GPU among them; CPU
    default ``cpus_per_task``) with ``env``, never retried; and ``room()``: how many such
    tasks the cluster runs at once now, its nodes as they are then (None: no limit; 0: no
    node left that can run one). InputError when it has no room for one now."""
    import ray

    resources = dict(resources or {})
    gpus = resources.pop("GPU", 0)
    cpus = resources.pop("CPU", cpus_per_task)
    remote = ray.remote(task).options(
        num_cpus=cpus, num_gpus=gpus, resources=resources or None, max_retries=0, runtime_env={"env_vars": env}
    )
    wanted = {k: v for k, v in {"CPU": cpus, "GPU": gpus, **resources}.items() if v}

    def room() -> int | None:
        total = ray.cluster_resources()  # of the nodes alive
        return min((int(total.get(k, 0) // v) for k, v in wanted.items()), default=None)

    if room() == 0:
        raise InputError(f"the Ray cluster has no room for a task of {wanted} (it has {ray.cluster_resources()})")
    return remote, room


def map_on_ray(
    task: Callable,
    args: list[tuple],
    *,
    address: str | None = None,
    cpus_per_task: int = 1,
    resources: dict[str, float] | None = None,
    device: str | None = None,
    done: Callable[[int, Any], None] = lambda index, result: None,
) -> list:
    """``task(*a)`` for each ``a`` of ``args`` as Ray tasks (a local Ray, or the cluster at
    ``address``), each with the serial path's P2G sum order and torch threads
    (:func:`serial_order`), so each gives the bits it gives in this process. Returns the
    results in ``args``' order (``done(index, result)`` as each arrives); a task's exception
    is raised here, the others cancelled."""
    with ray_session(address):
        import ray

        # all submitted at once: Ray queues those the cluster has no room for yet
        remote = remote_task(task, task_env(cpus_per_task, device, serial_order()), cpus_per_task, resources)[0]
        pending = {remote.remote(*a): i for i, a in enumerate(args)}
        results: dict[int, Any] = {}
        try:
            while pending:
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                index = pending.pop(ref)
                try:
                    results[index] = ray.get(ref)
                except ray.exceptions.RayTaskError as exc:  # the task's own exception, as the serial path raises it
                    raise (exc.cause if exc.cause is not None else exc) from None
                except ray.exceptions.RayError as exc:  # the worker died (killed, out of memory, node lost)
                    cause = " ".join(str(exc).split())[:300]
                    raise ClflowError(f"a Ray task died: {type(exc).__name__}: {cause}") from None
                done(index, results[index])
        finally:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
        return [results[i] for i in range(len(args))]


@contextlib.contextmanager
def ray_session(address: str | None = None, instead: str | None = "drop --parallel") -> Iterator[None]:
    """Ray for what runs inside (:func:`start_ray`; one already started is used), shut down
    after when started here: one session for all of a run's task maps (their workers reused).
    ``instead``: what to do without Ray, for the message (None: start_ray's default)."""
    started = start_ray(address, instead=instead)
    try:
        yield
    finally:
        if started:
            import ray

            ray.shutdown()
