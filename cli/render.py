"""``clflow render``: images and an orbit video of a 3DGS PLY file."""

from __future__ import annotations

import click

from clflow_cli.options import (
    FiniteFloat,
    InputFile,
    Numbers,
    OutputPath,
    count_option,
    given_options,
    max_output_option,
    out_option,
)

#: what only makes new views; a camera file's views are the file's
NEW_VIEW_OPTIONS = ("eye", "target", "up", "n_orbit", "elevation", "azimuth", "fov", "width", "height")


@click.command()
@click.argument("splats", type=InputFile())
@out_option("output_dir", "Folder for the PNG images (one per view).", default="renders", show_default=True)
@click.option("--cameras", "cameras_json", type=InputFile(),
              help="3DGS cameras.json; render its cameras (all, or those picked by --camera).")  # fmt: skip
@click.option("--transforms", "transforms_json", type=InputFile(),
              help="NeRF-style transforms.json; render its frames (all, or those picked by --camera).")  # fmt: skip
@click.option("--camera", "camera_keys", multiple=True, metavar="NAME|INDEX",
              help="Pick a camera of --cameras/--transforms by image name, file_path or index (repeatable).")  # fmt: skip
@click.option("--box", type=Numbers(6), metavar="X0,Y0,Z0,X1,Y1,Z1",
              help="Render only the Gaussians whose centres lie in this box (m).")  # fmt: skip
@click.option("--sphere", type=Numbers(4), metavar="X,Y,Z,R",
              help="Render only the Gaussians whose centres lie within R m of X,Y,Z.")  # fmt: skip
@click.option("--eye", type=Numbers(3), help="Look-at camera position X,Y,Z (m).")
@click.option("--target", type=Numbers(3), help="Look-at target X,Y,Z (m); default: the scene centre.")
@click.option("--up", type=Numbers(3), default="0,1,0", show_default=True,
              help="World up direction (+y, as scene configs; NeRF synthetic and Blender scenes: 0,0,1).")  # fmt: skip
@count_option("--orbit", "n_orbit", help="Render N views on a circle around the target.")
@click.option("--elevation", type=FiniteFloat(), default=20.0, show_default=True,
              help="Orbit / default view elevation above the horizontal plane, degrees.")  # fmt: skip
@click.option("--azimuth", type=FiniteFloat(), default=0.0, show_default=True, help="First orbit / default view azimuth, degrees.")  # fmt: skip
@click.option("--fov", type=FiniteFloat(1, 179), default=50.0, show_default=True,
              help="Horizontal field of view of generated views, degrees.")  # fmt: skip
@count_option('--width', default=512, help="Image width of generated views, pixels.")  # fmt: skip
@count_option('--height', default=512, help="Image height of generated views, pixels.")  # fmt: skip
@click.option("--background", type=Numbers(3, within=(0, 1)), metavar="R,G,B", default="0,0,0", show_default=True,
              help="Background colour R,G,B in [0, 1].")  # fmt: skip
@click.option("--sh-degree", type=click.IntRange(0, 3), help="Evaluate SH only up to this degree (default: all).")
@click.option("--video", type=OutputPath(file=True), help="Also write the views as a video (.mp4 or .gif).")
@click.option("--fps", type=FiniteFloat(min=0, min_open=True), default=24.0, show_default=True, help="Video frame rate.")  # fmt: skip
@click.option("--precision", type=click.Choice(["float32", "float64"]), default="float32", show_default=True,
              help="Compute precision of the rasteriser.")  # fmt: skip
@max_output_option
@click.pass_context
def render(ctx, splats, output_dir, **options) -> None:
    """Render SPLATS (a 3DGS PLY file, or a plain x y z [r g b] point cloud) to PNG images.

    The views are the cameras of --cameras or --transforms, a look-at camera (--eye,
    --target), an orbit of --orbit N views around the target, or by default one view that
    frames the scene (the centres between the 1st and 99th percentiles on each axis).
    --box and --sphere render a selection (both: the intersection), e.g. to check the
    object region before simulating it. Positions are in the PLY's world units (m).
    """
    import dataclasses

    from clflow.pipeline.runs import Views, render_splats
    from clflow_cli.progress import progress

    views = Views(**{field.name: options.pop(field.name) for field in dataclasses.fields(Views)})
    unused = given_options(ctx, lambda name: name in NEW_VIEW_OPTIONS) if views.from_file else []
    if unused:
        raise click.UsageError(f"{', '.join(unused)} make new views, --cameras/--transforms give theirs: drop them")
    # options: box, sphere, background, sh_degree, video, fps, precision, max_output_gb (render_splats' names)
    render_splats(splats, output_dir, views, **options, echo=click.echo, progress=progress)
