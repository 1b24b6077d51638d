"""What ``video: {generate: ...}`` may ask (checked with the config: its model folder, the
prompt template, frames enough for the simulated time) and the generation request it makes
(clflow.generate); clflow.pipeline.generated_video runs it."""

from __future__ import annotations

import math
import string
from typing import TYPE_CHECKING, Callable

from clflow.errors import InputError

if TYPE_CHECKING:
    from clflow.scene.config.settings import GenerateSettings, SimulationSettings

#: The physical-motion prompt, in the style of the paper's prompts for its generated guidance
#: videos ("the object ... is pushed ..."; a static camera, so that the video's optical flow
#: is the object's motion). Placeholders: {object}, {motion}, {material}.
PROMPT_TEMPLATE = (
    "A static camera shot. The {object} is {motion}, and moves and deforms like a real {material} "
    "object would. The camera and the background do not move."
)
PLACEHOLDERS = ("object", "motion", "material")


def _check_template(template: str, fail: Callable[[str, str], Exception]) -> None:
    try:
        names = [name for _, name, _, _ in string.Formatter().parse(template) if name is not None]
    except ValueError as exc:
        raise fail(
            "prompt_template",
            f"is not a valid template ({exc}); use {{object}}, {{motion}}, {{material}} and {{{{ }}}} for braces",
        ) from None
    unknown = [n for n in names if n not in PLACEHOLDERS]
    if unknown:
        raise fail(
            "prompt_template",
            f"has the unknown placeholder {{{unknown[0]}}}; known: {', '.join('{' + p + '}' for p in PLACEHOLDERS)}",
        )


def generate_request(settings: GenerateSettings, simulation: SimulationSettings, info, prompt: str):
    """The clflow.generate.GenerateRequest: frames default to enough to cover the simulated
    time at the video's frame rate (default simulation.fps), as many as the model makes."""
    from clflow.generate import GenerateRequest

    fps = settings.fps or simulation.fps
    frames = settings.frames
    if frames is None:
        needed = math.ceil(simulation.frames * fps / simulation.fps - 1e-9) + 1
        step = info.frame_step
        frames = 1 + math.ceil((needed - 1) / step) * step
    return GenerateRequest(
        prompt=prompt,
        negative_prompt=settings.negative_prompt,
        frames=frames,
        fps=fps,
        seed=settings.seed,
        steps=settings.steps,
        guidance_scale=settings.guidance_scale,
        size=settings.size,
        fit=settings.fit,
        output_size="image",
        cpu_offload=settings.cpu_offload,
        vae_tiling=settings.vae_tiling,
        vae_slicing=settings.vae_slicing,
    )


def check_settings(settings: GenerateSettings, simulation: SimulationSettings, fail: Callable[[str, str], Exception]):
    """Check ``video.generate`` against its model folder (JSON files only) and the simulated
    time; ``fail(key, message)`` makes the error naming the key. Returns the model's info."""
    from clflow.generate import check_request, inspect_model

    try:
        info = inspect_model(settings.model)
    except InputError as exc:
        raise fail("model", str(exc)) from None
    if settings.prompt_template is not None:
        _check_template(settings.prompt_template, fail)
    # the motion prompt is made later, from the scene: a stand-in here (none for an image-only
    # model, which would warn that it ignores a prompt)
    request = generate_request(
        settings, simulation, info, (settings.prompt or "a motion prompt") if info.uses_prompt else ""
    )
    duration = simulation.frames / simulation.fps
    if (request.frames - 1) / request.fps < duration - 1e-9:
        raise fail(
            "frames",
            f"{request.frames} frames at {request.fps:g} fps last {(request.frames - 1) / request.fps:.3g}"
            f" s, the simulation {duration:.3g} s: give at least "
            f"{math.ceil(duration * request.fps - 1e-9) + 1}",
        )
    if settings.prompt is not None and info.uses_prompt and not settings.prompt.strip():
        raise fail("prompt", "is empty: drop it for the motion prompt from the forces, or describe the motion")
    try:
        check_request(info, request)
    except InputError as exc:
        key, _, rest = str(exc).partition(": ")
        known = {
            "frames": "frames",
            "size": "size",
            "prompt": "prompt",
            "guidance scale": "guidance_scale",
            "fps must be positive, got": "fps",
            "VAE tiling": "vae_tiling",
            "VAE slicing": "vae_slicing",
        }
        if key in known:
            raise fail(known[key], rest) from None
        raise fail("", str(exc)) from None
    return info
