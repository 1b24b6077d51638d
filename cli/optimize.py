"""``clflow optimize``: material parameters of a scene config from its guidance video."""

from __future__ import annotations

import click

from clflow_cli.options import InputFile, budget_option, max_substeps_option, out_option, set_option
from clflow_cli.sweep import parse_resources, with_ray_options


@click.command("optimize")
@click.argument("config", type=InputFile())
@click.option("--resume", is_flag=True, help="Continue from OUT/checkpoint.json (after Ctrl-C or a kill).")
@click.option("--iterations", type=click.IntRange(min=1), default=None,
              help="Override optimize.iterations of the config.")  # fmt: skip
@out_option("output", "Results folder (default: the config's output).")
@set_option("Set a config key, the value read as YAML, e.g. --set material.parameters.youngs_modulus=2e4 "
            "(repeatable; checked like the file). --resume needs the same --set as the run it continues.")  # fmt: skip
@max_substeps_option("Refuse a run needing more substeps per frame (default: simulation.max_substeps, 2000).")
@budget_option("The optimisation's wall time (600, 10min, 1.5h): the main grid is the finest whose predicted run fits, "
               "timed on this device from the search's grid up (optimize.budget; docs/pipeline.md).")  # fmt: skip
@click.option("--force-video", is_flag=True,
              help="Optimise even when the guidance checks fail (no motion, noise, a camera that does not fit); "
                   "the failures are warned about and recorded in metrics.json.")  # fmt: skip
@click.option("--parallel", is_flag=True,
              help="Run the material hypotheses' searches and the search starts' polishes as Ray tasks "
                   "(clflow[sweep]; a local Ray on this machine's cores, or --address); the results are the serial "
                   "path's.")  # fmt: skip
@with_ray_options
@click.pass_context
def optimize(ctx, config, parallel, address, cpus_per_task, resources, budget, **settings):
    """Optimise the material parameters of CONFIG (YAML/JSON scene config) so that the
    simulated optical flow matches the guidance video's.

    Writes into the output folder: params.json (final parameters, SI), metrics.json,
    history.json, loss.png, comparison.mp4 and checkpoint.json (after every iteration)."""
    from clflow.pipeline.runs import run_optimization
    from clflow_cli.progress import iteration_bar, note

    ray = None
    if parallel:
        ray = {
            "address": address,
            "cpus_per_task": cpus_per_task,
            "resources": parse_resources(resources),
            "device": ctx.obj.device_spec if ctx.obj else None,
        }
    elif address or resources:
        raise click.UsageError("--address and --resources go with --parallel")
    if budget is not None:  # as the config key, so that the resume command carries it
        settings["overrides"] = (*settings["overrides"], f"optimize.budget.seconds={budget:g}")
    # settings: resume, iterations, output, overrides, max_substeps, force_video (run_optimization's names)
    run_optimization(config, **settings, echo=click.echo, note=note, bar=iteration_bar, parallel=ray)
