"""``clflow pacnerf``: a PAC-NeRF-style multi-camera capture as a clflow scene + guidance video."""

from __future__ import annotations

import click

from clflow_cli.options import InputFile


@click.command("pacnerf")
@click.argument("data", type=click.Path())
@click.argument("splats", type=click.Path())
@click.option("-o", "--output-dir", required=True, type=click.Path(file_okay=False),
              help="Scene folder: config.yaml, scene.ply, camera.json, the guidance video (and object.png).")  # fmt: skip
@click.option("--camera", type=click.IntRange(min=0), default=0, show_default=True,
              help="The camera whose frames become the guidance video.")  # fmt: skip
@click.option("--config", type=InputFile(),
              help="PAC-NeRF config (.py, read without running it, or .json): material and its initial guess, ground, "
                   "gravity, frame_dt, the parameters to fit. Without it the material is left to the query.")  # fmt: skip
@click.option("--box", type=float, nargs=6, metavar="X0 Y0 Z0 X1 Y1 Z1",
              help="Object box in m (default: around the Gaussians at least 0.1 opaque).")  # fmt: skip
@click.option("--ground", type=float, help="Height of a sticky ground plane, m (y up); over the config's.")
@click.option("--background", type=click.Choice(["white", "black"]), default="white", show_default=True,
              help="Colour behind the masked object in the guidance video; clflow renders its scenes over white.")  # fmt: skip
@click.option("--masks", type=click.Path(file_okay=False),
              help="Folder of masks named like the images (white = object); default: the images' alpha channel.")  # fmt: skip
@click.option("--fps", type=click.FloatRange(min=0, min_open=True),
              help="Frame rate (default: the config's 1 / frame_dt, else the index's times).")  # fmt: skip
@click.option("--prompt", default="", help="Text about the object for the material query (without --config).")
@click.option("--optimize", multiple=True, metavar="NAME",
              help="A parameter to fit (repeatable); default: the config's physical_params.")  # fmt: skip
@click.option("--video", type=click.Choice(["mp4", "mkv"]), default="mp4", show_default=True,
              help="Guidance video format: H.264 or lossless FFV1.")  # fmt: skip
def pacnerf(data, splats, output_dir, background, video, **options):
    """Turn the multi-camera capture DATA (PAC-NeRF's layout: all_data.json and
    r_CAMERA_FRAME.png images) and SPLATS, the reconstruction of its frame 0
    (`clflow reconstruct DATA --frame 0 -o SPLATS`), into a scene folder for
    `clflow optimize`: the config, the splats, the chosen camera and its frames as the
    guidance video."""
    from clflow_datasets.pacnerf import make_scene

    rgb = (0.0, 0.0, 0.0) if background == "black" else (1.0, 1.0, 1.0)
    # the other options are make_scene's keywords (camera, config, box, ground, masks, fps, prompt, optimize)
    summary = make_scene(data, splats, output_dir, background=rgb, video=f"guidance.{video}", **options)
    click.echo(
        f"camera {options['camera']}: {summary['frames']} frames at {summary['fps']:g} fps (from {summary['fps_from']}); "
        f"material {summary['material']}; fitting {', '.join(summary['optimize']) or 'nothing yet'}"
    )
    if summary["optimize"]:
        click.echo(f"next: clflow optimize {summary['config']}")
    else:
        click.echo(
            f"next: clflow optimize {summary['config']} --set optimize.parameters=[NAME,...] "
            f"(the parameters of the material the query picks)"
        )
