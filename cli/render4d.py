"""``clflow render4d``: the simulated 4D scene from the guidance camera and novel viewpoints."""

from __future__ import annotations

import click

from clflow_cli.main import FiniteFloat, max_output_option


@click.command("render4d")
@click.argument("simulation", type=click.Path(file_okay=False))
@click.option("--out", "-o", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Output folder [default: SIMULATION/render4d].")
@click.option("--views", type=click.IntRange(min=0), default=0, show_default=True,
              help="Also render N fixed novel viewpoints on the orbit circle.")
@click.option("--turns", type=FiniteFloat(), default=1.0, show_default=True,
              help="Turns of the orbiting camera over the sequence.")
@click.option("--format", "video_format", type=click.Choice(["mp4", "gif"]), default="mp4", show_default=True,
              help="Video format.")
@max_output_option
def render4d(simulation, out_dir, views, turns, video_format, max_output_gb):
    """Render the per-frame Gaussians of SIMULATION (the folder `clflow simulate CONFIG`
    wrote) over time: from the guidance camera, from a camera orbiting the object while the
    simulation runs and from --views fixed novel viewpoints; PNG frames and a video each."""
    from pathlib import Path

    from clflow.limits import check_output
    from clflow.pipeline.frames4d import load_frames, render_4d, render_4d_frames, render_4d_size
    from clflow_cli.progress import progress

    frames = load_frames(simulation)
    out = Path(out_dir) if out_dir else Path(simulation) / "render4d"
    check_output(out, render_4d_size(frames, views), max_output_gb,
                 f"{views + 2:,} sequences of {frames.frame_count} frames", "render fewer --views")
    with progress(render_4d_frames(frames, views), "rendering") as advance:
        videos = render_4d(frames, out, views=views, turns=turns, video_format=video_format, advance=advance)
    for video in videos:
        click.echo(f"wrote {video} and {video.with_suffix('')}/*.png ({frames.frame_count} frames)")
