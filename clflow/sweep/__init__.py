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
driver's (:func:`serial_order`) so a task gives the bits the serial path gives. The modules:
``spec`` (the SPEC and its runs), ``runner`` (one run, serial or on Ray) and ``study`` (the
sweep, its folders and summary).

    spec = load_spec("sweep.yaml")
    summary = sweep(spec, Path("out"), serial=True)       # or serial=False: Ray
"""

from clflow.sweep.runner import execute, run_on_ray, run_serial, sysid_on_ray
from clflow.sweep.spec import COMMANDS, Run, Spec, load_spec, parse_spec
from clflow.sweep.study import markdown, sweep

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
    "sysid_on_ray",
]
