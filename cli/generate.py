"""``clflow generate IMAGE --prompt TEXT -o VIDEO``: a guidance video from an image-to-video
diffusion model (the optional extra ``clflow[video]``; docs/generate.md)."""

from pathlib import Path

import click

from clflow_cli.options import FiniteFloat, InputFile, OutputPath, out_option

# the same names as clflow.generate.FITS / OUTPUT_SIZES, written out so --help imports nothing heavy
FIT_CHOICES = ("pad", "crop")
OUTPUT_SIZE_CHOICES = ("image", "model")


def _size(ctx, param, value):
    if value is None:
        return None
    from clflow.errors import InputError
    from clflow.generate import parse_size

    try:
        return parse_size(value)
    except InputError as exc:
        raise click.BadParameter(str(exc).removeprefix("size "), ctx, param) from None


@click.command()
@click.argument("image", type=InputFile(path_type=Path))
@click.option("--model", "model_path", required=True, type=click.Path(path_type=Path), metavar="FOLDER",
              help="A local diffusers model folder: CogVideoX image-to-video (prompt + image) or Stable Video "
              "Diffusion (image only), told apart by its model_index.json. Never downloaded.")  # fmt: skip
@click.option("--prompt", default="", help="The motion to show (CogVideoX; SVD takes none).")
@click.option("--negative-prompt", default="", help="What not to show (CogVideoX).")
@out_option("output", "The video (.mp4, .gif, ...); the run's record goes beside it as .json.", required=True,
            type=OutputPath(file=True, path_type=Path))  # fmt: skip
@click.option("--frames", type=click.IntRange(min=2), default=None,
              help="Frames to generate [default: the model's, e.g. 49 for CogVideoX, 14 or 25 for SVD].")  # fmt: skip
@click.option("--fps", type=FiniteFloat(min=0, min_open=True), default=None,
              help="Frame rate of the video (and SVD's fps conditioning) [default: the model's, 8 or 7].")  # fmt: skip
@click.option("--seed", type=click.IntRange(min=0, max=2**63 - 1), default=0, show_default=True,
              help="Random seed: the same seed gives the same frames on the same device.")  # fmt: skip
@click.option("--steps", type=click.IntRange(min=1), default=None,
              help="Denoising steps [default: 50 for CogVideoX, 25 for SVD].")  # fmt: skip
@click.option("--guidance-scale", type=FiniteFloat(min=0), default=None,
              help="Classifier-free guidance (SVD: the last frame's; the first is 1) [default: 6 / 3].")  # fmt: skip
@click.option("--size", default=None, callback=_size, metavar="WxH",
              help="Size the model generates at [default: the model's, e.g. 720x480 or 1024x576].")  # fmt: skip
@click.option("--fit", type=click.Choice(FIT_CHOICES), default="pad", show_default=True,
              help="pad: the whole image, scaled into the model's frame and padded with its edge pixels; "
              "crop: the frame filled, the overflow cut off.")  # fmt: skip
@click.option("--output-size", type=click.Choice(OUTPUT_SIZE_CHOICES), default="image", show_default=True,
              help="image: frames cut to the image's area and scaled back to its pixels (a guidance video "
              "for the camera the image was taken with); model: the frames as generated.")  # fmt: skip
@click.option("--cpu-offload", is_flag=True, help="Keep only the running model on the GPU (diffusers' model CPU "
              "offload; needs accelerate; ignored on a CPU run).")  # fmt: skip
@click.option("--vae-tiling", is_flag=True, help="Decode in tiles (less memory; CogVideoX).")
@click.option("--vae-slicing", is_flag=True, help="Decode one video at a time (less memory; CogVideoX).")
def generate(image, model_path, output, **request_options) -> None:
    """Make a guidance video from IMAGE (the object as the guidance camera sees it) with an
    image-to-video diffusion model, for `clflow optimize`'s `video:`.

    Runs on CUDA when torch sees a GPU, else on the CPU (slow: a warning gives the expected
    time). Needs the optional extra: pip install 'clflow[video]'.
    """
    import time

    from clflow.fileio import check_output_file
    from clflow.generate import (
        GenerateRequest,
        check_request,
        generate_video,
        inspect_model,
        load_image,
        require_extra,
        write_generated,
    )
    from clflow.limits import check_output
    from clflow.media import VIDEO_CODECS

    start = time.perf_counter()
    if output.suffix.lower() not in (*VIDEO_CODECS, ".gif"):
        raise click.BadParameter(
            f"{output}: unsupported video suffix {output.suffix!r}; use .gif or one of {', '.join(VIDEO_CODECS)}",
            param_hint="'-o'",
        )
    # everything is checked before torch loads a weight: the folder, the request, the image, the output
    info = inspect_model(model_path)
    request = GenerateRequest(**request_options)  # the other options are its fields, by name
    resolved = check_request(info, request)
    pixels = load_image(image)
    check_output(output.resolve().parent)
    check_output_file(output.with_suffix(".json"))  # the record beside it: not over a user's file
    require_extra()
    click.echo(
        f"{info.family.name} ({model_path}): {resolved.frames} frames at {resolved.size[0]}x"
        f"{resolved.size[1]}, {resolved.steps} steps, seed {request.seed}",
        err=True,
    )

    def progress(step: int, total: int) -> None:
        click.echo(f"step {step}/{total}", err=True)

    video, record = generate_video(pixels, info, request, progress=progress)
    record["image"] = str(image.resolve())
    meta = write_generated(output, video, record, total_s=time.perf_counter() - start)
    click.echo(
        f"wrote {output} ({video.shape[0]} frames, {video.shape[2]}x{video.shape[1]}, {record['fps']:g} fps) and {meta}"
    )
