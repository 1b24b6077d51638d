"""Running the model: the optional extra imported, the diffusers pipeline loaded with its
memory options, the denoising run with its progress, the time estimate and the run's record."""

from __future__ import annotations

import logging
import os
import time
import warnings
from typing import Callable

import numpy as np

from clflow.environment import environment
from clflow.errors import ClflowError, InputError
from clflow.generate.frames import check_image, fit_image, restore_frames
from clflow.generate.models import ModelInfo
from clflow.generate.request import GenerateRequest, Resolved, check_request
from clflow.limits import format_duration

log = logging.getLogger("clflow.generate")

EXTRA = "video"
INSTALL_HINT = f"pip install 'clflow[{EXTRA}]' (from a checkout: pip install -e '.[{EXTRA}]')"
#: CPU throughput assumed by the up-front time estimate (FLOP/s per core, float32 matmuls);
#: the estimate is replaced by a measured one after the first denoising step.
CPU_FLOPS_PER_CORE = 20e9


def require_extra():
    """Import diffusers and transformers, or say which extra installs them."""
    try:
        import diffusers  # noqa: F401
        import transformers  # noqa: F401
    except ImportError as exc:
        raise InputError(
            f"clflow generate needs the optional extra '{EXTRA}' (diffusers, transformers, "
            f"accelerate), which is not installed ({exc.name or exc}): {INSTALL_HINT}"
        ) from None
    return diffusers


def estimate_seconds(info: ModelInfo, resolved: Resolved, cores: int | None = None) -> float:
    """A rough CPU time: 2 FLOPs per denoiser weight and token per step (x2 with classifier-free
    guidance) at :data:`CPU_FLOPS_PER_CORE` per core. An order of magnitude, no more."""
    params = info.weight_bytes / 2  # released checkpoints are half precision
    w, h = resolved.size
    latent_frames = (resolved.frames - 1) // max(1, info.frame_step // 2) + 1 if info.uses_prompt else resolved.frames
    tokens = latent_frames * (w // info.size_multiple) * (h // info.size_multiple)
    if not info.uses_prompt:  # a UNet: convolutions over every latent pixel; tokens at 1/2 of a 2x2 patch grid
        tokens = latent_frames * (w // 8) * (h // 8) / 4
    passes = 2 if resolved.guidance_scale > 1 else 1
    flops = 2 * params * tokens * resolved.steps * passes
    return flops / (CPU_FLOPS_PER_CORE * (cores or os.cpu_count() or 1))


def generate_video(
    image: np.ndarray,
    info: ModelInfo,
    request: GenerateRequest,
    *,
    progress: Callable[[int, int], None] | None = None,
    device: str | None = None,
) -> tuple[np.ndarray, dict]:
    """Run the model on ``image`` [H, W, 3] uint8: [T, H', W', 3] uint8 frames and the run's
    record (everything but the output path). ``device``: a torch device, default CUDA when
    torch sees one, else the CPU (with a warning giving the expected time)."""
    resolved = check_request(info, request)
    check_image(image, "the image")
    require_extra()
    import torch

    from clflow.media import to_uint8

    t0 = time.perf_counter()
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cpu":
        _warn_cpu_time(info, resolved)
    dtype = torch.float32 if device == "cpu" else (torch.bfloat16 if info.uses_prompt else torch.float16)
    pipe = _load(info, dtype)
    options = _memory_options(pipe, resolved.request, device)
    if "model CPU offload" not in options:
        pipe.to(device)
    pipe.set_progress_bar_config(disable=True)
    load_s = time.perf_counter() - t0

    model_image, placement = fit_image(image, resolved.size, resolved.request.fit)
    start = time.perf_counter()
    out = _run_pipeline(pipe, info, resolved, model_image, device, progress)
    generate_s = time.perf_counter() - start
    video = np.asarray(out.frames[0], np.float32)  # [T, h, w, 3] in [0, 1]
    if video.shape[0] != resolved.frames:  # check_request's rule for this model is wrong: say so
        raise ClflowError(
            f"{info.path}: the model made {video.shape[0]} frames, not the {resolved.frames} asked for; "
            f"please report this with the model's model_index.json"
        )
    frames = to_uint8(video)
    if resolved.request.output_size == "image":
        frames = restore_frames(frames, placement)
    timings = {"load_s": load_s, "generate_s": generate_s}
    return frames, _record(info, resolved, frames, placement, image, device, dtype, options, timings)


def _record(info, resolved, frames, placement, image, device, dtype, options, timings) -> dict:
    """The run's record: request, model, sizes, placement, device, timings (s), versions."""
    load_s, generate_s = timings["load_s"], timings["generate_s"]
    return {
        "prompt": resolved.request.prompt if info.uses_prompt else None,
        "negative_prompt": resolved.request.negative_prompt or None,
        "model": {"path": str(info.path), "class": info.class_name, "family": info.family.name},
        "seed": resolved.request.seed,
        "steps": resolved.steps,
        "guidance_scale": resolved.guidance_scale,
        "frames": int(frames.shape[0]),
        "fps": resolved.fps,
        "model_size": list(resolved.size),
        "size": [int(frames.shape[2]), int(frames.shape[1])],
        "fit": resolved.request.fit,
        "output_size": resolved.request.output_size,
        "placement": {"box": list(placement.box), "image_size": list(image.shape[1::-1])},
        "device": device,
        "dtype": str(dtype).removeprefix("torch."),
        "memory_options": options,
        "timings": {
            "load_s": round(load_s, 3),
            "generate_s": round(generate_s, 3),
            "per_step_s": round(generate_s / resolved.steps, 3),
        },
        "versions": environment(("diffusers", "transformers", "accelerate"), opencl=False),
    }


def _warn_cpu_time(info: ModelInfo, resolved) -> None:
    """Warn that generating on the CPU is slow, with a rough estimate of how slow."""
    log.warning(
        "no CUDA device: generating on the CPU (%d cores) takes about %s for %s at %dx%d, %d frames, "
        "%d steps (a rough estimate from the weights' size; measured after the first step)",
        os.cpu_count() or 1,
        format_duration(estimate_seconds(info, resolved)),
        info.path.name,
        *resolved.size,
        resolved.frames,
        resolved.steps,
    )


def _run_pipeline(pipe, info: ModelInfo, resolved, model_image: np.ndarray, device: str, progress):
    """The diffusers pipeline's output for ``model_image`` [h, w, 3] uint8 (frames in [0, 1]);
    ``progress(step, steps)`` after each denoising step."""
    import torch
    from PIL import Image

    step_times: list[float] = []
    start = time.perf_counter()

    def on_step(pipeline, i, t, kwargs):
        step_times.append(time.perf_counter())
        if progress:
            progress(i + 1, resolved.steps)
        if i == 0 and device == "cpu" and resolved.steps > 1:
            per_step = step_times[0] - start
            log.info(
                "first step took %.1f s: about %s to go", per_step, format_duration(per_step * (resolved.steps - 1))
            )
        return {}

    generator = torch.Generator(device="cpu").manual_seed(resolved.request.seed)
    w, h = resolved.size
    common = dict(
        image=Image.fromarray(model_image),
        height=h,
        width=w,
        num_frames=resolved.frames,
        num_inference_steps=resolved.steps,
        generator=generator,
        output_type="np",
        callback_on_step_end=on_step,
        callback_on_step_end_tensor_inputs=[],
    )
    with torch.inference_mode():
        if info.uses_prompt:
            return pipe(
                prompt=resolved.request.prompt,
                negative_prompt=resolved.request.negative_prompt or None,
                guidance_scale=resolved.guidance_scale,
                max_sequence_length=info.max_text_tokens,
                **common,
            )
        return pipe(
            min_guidance_scale=1.0,
            max_guidance_scale=resolved.guidance_scale,
            fps=max(1, round(resolved.fps)),
            **common,
        )


def _load(info: ModelInfo, dtype):
    diffusers = require_extra()
    import transformers

    for library in (diffusers, transformers):  # clflow reports progress itself; -v keeps their logs
        library.utils.logging.disable_progress_bar()
        if not log.isEnabledFor(logging.DEBUG):
            library.utils.logging.set_verbosity_error()
    cls = getattr(diffusers, info.class_name)
    try:
        with warnings.catch_warnings():  # newer diffusers call it dtype; torch_dtype works in all
            warnings.filterwarnings("ignore", message=".*torch_dtype.*", category=FutureWarning)
            return cls.from_pretrained(str(info.path), local_files_only=True, torch_dtype=dtype)
    except (OSError, ValueError, KeyError, TypeError) as exc:  # a damaged file the layout check could not see
        raise InputError(
            f"{info.path}: diffusers could not load the {info.family.name} model: {' '.join(str(exc).split())[:400]}"
        ) from None


def _memory_options(pipe, request: GenerateRequest, device: str) -> list[str]:
    options = []
    if request.cpu_offload:
        if device == "cpu":
            log.warning("--cpu-offload moves models between the GPU and the CPU: ignored on a CPU run")
        else:
            pipe.enable_model_cpu_offload(device=device)
            options.append("model CPU offload")
    if request.vae_tiling:
        pipe.vae.enable_tiling()
        options.append("VAE tiling")
    if request.vae_slicing:
        pipe.vae.enable_slicing()
        options.append("VAE slicing")
    return options
