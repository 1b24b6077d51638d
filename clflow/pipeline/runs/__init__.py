"""The pipeline's steps as whole runs: what ``clflow optimize``, ``clflow simulate`` (a scene
config, or particles) and ``clflow render4d`` do, for the CLI, ``clflow demo`` and
``clflow sweep`` alike.

The CLI only parses options and says how to show progress: ``echo(line)`` for results
(stdout), ``note(line)`` for progress lines (stderr) and ``bar(total, done)``, a context
manager yielding ``advance(row)``; the defaults show nothing. Ctrl-C during an optimisation
raises KeyboardInterrupt with a one-line message saying what was saved and how to resume.
"""

from clflow.pipeline.runs.optimize import CACHES, RESULTS, RESUMABLE, RUN_ENTRIES, resume_command, run_optimization
from clflow.pipeline.runs.progress import format_row, iteration_lines
from clflow.pipeline.runs.records import input_files, read_params_record
from clflow.pipeline.runs.simulate import (
    PARTICLE_ENTRIES,
    SIMULATION_ENTRIES,
    ParticleRun,
    render_simulation_4d,
    simulate_particles,
    simulate_scene,
)

__all__ = [
    "CACHES",
    "PARTICLE_ENTRIES",
    "RESULTS",
    "RESUMABLE",
    "RUN_ENTRIES",
    "SIMULATION_ENTRIES",
    "ParticleRun",
    "format_row",
    "input_files",
    "iteration_lines",
    "read_params_record",
    "render_simulation_4d",
    "resume_command",
    "run_optimization",
    "simulate_particles",
    "simulate_scene",
]
