"""``clflow render4d``: the simulated 4D scene from the guidance camera and novel viewpoints."""

from __future__ import annotations

import click

from clflow_cli.options import FiniteFloat, max_output_option, out_option


@click.command("render4d")
@click.argument("simulation", type=click.Path(file_okay=False))
@out_option("out_dir", "Output folder [default: SIMULATION/render4d].")
@click.option("--views", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also render N fixed novel viewpoints on the orbit circle.")  # fmt: skip
@click.option("--turns", type=FiniteFloat(), default=1.0, show_default=True,
              help="Turns of the orbiting camera over the sequence.")  # fmt: skip
@click.option("--format", "video_format", type=click.Choice(["mp4", "gif"]), default="mp4", show_default=True,
              help="Video format.")  # fmt: skip
@max_output_option
def render4d(simulation, out_dir, views, turns, video_format, max_output_gb):
    """Render the per-frame Gaussians of SIMULATION (the folder `clflow simulate CONFIG`
    wrote) over time: from the guidance camera, from a camera orbiting the object while the
    simulation runs and from --views fixed novel viewpoints; PNG frames and a video each."""
    from clflow.pipeline.runs import render_simulation_4d
    from clflow_cli.progress import progress

    render_simulation_4d(
        simulation, out_dir, views, turns, video_format, max_output_gb, progress=progress, echo=click.echo
    )
