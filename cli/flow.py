"""``clflow flow VIDEO``: observed optical flow of a guidance video, written to disk."""

import click

from clflow_cli.options import FiniteFloat, InputFile, out_option, pixel_box_option


@click.command()
@click.argument("video", type=click.Path(path_type=str))
@out_option("output", "Output folder. Default: VIDEO's name + '_flow' in the current folder.")
@click.option("--method", type=click.Choice(["dis", "farneback", "raft"]), default="dis", show_default=True,
              help="Optical flow backend (raft only with --raft-weights).")  # fmt: skip
@click.option("--preset", type=click.Choice(["ultrafast", "fast", "medium", "fine"]), default="fine", show_default=True,
              help="DIS quality preset (clflow.flow.optical_flow.DIS_PRESETS).")  # fmt: skip
@click.option("--raft-weights", type=InputFile(path_type=str), default=None,
              help="torchvision RAFT-large state dict already on disk (nothing is downloaded).")  # fmt: skip
@click.option("--fps", type=FiniteFloat(min=0, min_open=True), default=None,
              help="Frame rate (frames/s); needed for an image folder's times.")  # fmt: skip
@click.option("--start", type=FiniteFloat(min=0), default=0.0, show_default=True, help="First time to use (s).")
@click.option("--end", type=FiniteFloat(min=0, min_open=True), default=None,
              help="End of the time window (s, exclusive).")  # fmt: skip
@click.option("--stride", type=click.IntRange(min=1), default=1, show_default=True, help="Use every N-th frame.")
@click.option("--sim-fps", type=FiniteFloat(min=0, min_open=True), default=None,
              help="Resample (nearest frame) to this rate, e.g. the simulation's frames per second.")  # fmt: skip
@click.option("--mask", "mask_image", type=InputFile(path_type=str), default=None,
              help="Object mask image (object where grey > 127), the video's size.")  # fmt: skip
@pixel_box_option("Object box in pixels (x right, y down).")
@click.option("--video/--no-video", "write_panels_video", default=True, show_default=True,
              help="Also write flow.mp4 (frame | colour-coded flow; played at 24 fps when the rate is unknown).")  # fmt: skip
@click.pass_obj
def flow(obj, video, output, write_panels_video, **options):
    """Optical flow between consecutive frames of VIDEO (a video file or an image folder).

    Writes OUT/flow.npz (flow [T-1, H, W, 2] px, valid [T-1, H, W] = forward-backward
    consistent and inside the object mask, times [T] s), OUT/flo/flow_NNNN.flo, and
    OUT/png/flow_NNNN.png panels (frame | flow) plus OUT/flow.mp4; all or nothing, an earlier
    run's files (its extra frames too) replaced as a whole.
    """
    from pathlib import Path

    from clflow.errors import InputError
    from clflow.pipeline.runs import export_flow
    from clflow_cli.progress import progress

    # options: method, preset, raft_weights, fps, start, end, stride, sim_fps, mask_image, box (export_flow's names)
    if options["mask_image"] and options["box"]:
        raise InputError("give either --mask or --box, not both")
    timed = [name for name, key in (("--start", "start"), ("--end", "end"), ("--sim-fps", "sim_fps")) if options[key]]
    if timed and options["fps"] is None and Path(video).is_dir():  # known before its frames are read
        raise click.UsageError(f"{video} is an image folder, which has no frame rate: {', '.join(timed)} needs --fps")
    export_flow(video, output, **options, panels_video=write_panels_video, echo=click.echo, progress=progress)
