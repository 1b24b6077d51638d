"""The pipeline's steps as whole runs: what ``clflow optimize``, ``clflow simulate`` (a scene
config, or particles), ``clflow render4d``, ``clflow render`` (a PLY from chosen views),
``clflow reconstruct`` and ``clflow flow`` (a video's observed flow) do, for the CLI,
``clflow demo`` and ``clflow sweep`` alike.

The CLI only parses options and says how to show progress: ``echo(line)`` for results
(stdout), ``note(line)`` for progress lines (stderr) and ``bar(total, done)``, a context
manager yielding ``advance(row)``; the defaults show nothing. Ctrl-C during an optimisation
raises KeyboardInterrupt with a one-line message saying what was saved and how to resume.
"""

from clflow.pipeline.runs.flow import export_flow
from clflow.pipeline.runs.optimize import (
    CACHES,
    RESULTS,
    RESUMABLE,
    RUN_ENTRIES,
    resume_command,
    run_optimization,
    write_results,
)
from clflow.pipeline.runs.progress import format_row, iteration_lines
from clflow.pipeline.runs.reconstruct import RECONSTRUCTION_ENTRIES, reconstruct_images, reconstruct_photo
from clflow.pipeline.runs.records import input_files, read_params_record
from clflow.pipeline.runs.render import VIDEO_SUFFIXES, Views, render_splats
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
    "RECONSTRUCTION_ENTRIES",
    "RESULTS",
    "RESUMABLE",
    "RUN_ENTRIES",
    "SIMULATION_ENTRIES",
    "VIDEO_SUFFIXES",
    "Views",
    "ParticleRun",
    "export_flow",
    "format_row",
    "input_files",
    "iteration_lines",
    "read_params_record",
    "reconstruct_images",
    "reconstruct_photo",
    "render_simulation_4d",
    "render_splats",
    "resume_command",
    "run_optimization",
    "simulate_particles",
    "simulate_scene",
    "write_results",
]
