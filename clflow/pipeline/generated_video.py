"""``video: {generate: ...}``: the guidance video made by an image-to-video model as the first
step of ``clflow optimize`` (docs/generate.md), cached by a hash of everything that makes it.

    cfg = ensure_guidance_video(cfg)   # cfg.video: output/generated/guidance-<hash>.mp4

The input image is ``video.generate.image``, or else the splat scene rendered from the
guidance camera (the paper's set-up: the model animates the view the optimiser compares
with). The prompt is ``video.generate.prompt``, or else :data:`PROMPT_TEMPLATE` filled from
the scene's forces and initial velocity (:func:`motion_prompt`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path
from typing import Callable

import numpy as np

from clflow.errors import InputError
from clflow.fileio.reading import parse_json
from clflow.scene.config import SceneConfig
from clflow.scene.video_settings import PROMPT_TEMPLATE, check_settings, generate_request

log = logging.getLogger(__name__)

CACHE_FOLDER = "generated"  # under the config's output folder


def _direction(vector) -> str:
    """Words for a direction in the simulation frame (+y up), for the default view: a camera
    looking along -z with +x to its right (other views: write the prompt yourself)."""
    words = (("to the right", "to the left"), ("upwards", "downwards"), ("towards the camera", "away from the camera"))
    v = np.asarray(vector, float)
    big = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.5 * np.abs(v).max() > 0]
    return " and ".join(words[i][0 if v[i] > 0 else 1] for i in big[:2])


def motion_prompt(cfg: SceneConfig, template: str | None = None, object_name: str | None = None) -> str:
    """The prompt for the config's motion: the initial velocity ("thrown ..."; objects thrown
    apart each by name), each force or acceleration stage ("pushed to the left", with its
    start time when it is not at once), else a fall under gravity; the material the objects'
    ("elastic", "elastic and sand")."""
    gen = cfg.generate
    template = template or (gen.prompt_template if gen and gen.prompt_template else PROMPT_TEMPLATE)
    object_name = object_name or (gen.object if gen else "object")
    parts = []
    thrown = {o.velocity for o in cfg.objects}
    if len(thrown) == 1:  # one object, or all thrown alike
        parts += [f"thrown {_direction(v)}" for v in thrown if any(v)]
    else:
        parts += [f"{o.name} thrown {_direction(o.velocity)}" for o in cfg.objects if any(o.velocity)]
    for stage in cfg.forces:
        if not any(stage.vector):
            continue
        when = f" after {stage.start:g} s" if stage.start > 0 else ""
        how = "pushed" if stage.end - stage.start > 0.25 or math.isinf(stage.end) else "hit and pushed"
        parts.append(f"{how} {_direction(stage.vector)}{when}")
    if not parts:
        parts.append("falling under gravity" if any(cfg.simulation.gravity) else "at rest")
    motion = ", then ".join(parts)
    types = dict.fromkeys(o.material.type if o.material.type != "query" else "physical" for o in cfg.objects)
    material = " and ".join(types)
    return template.format(object=object_name, motion=motion, material=material.replace("_", " "))


def guidance_image(cfg: SceneConfig) -> np.ndarray:
    """The model's input: ``video.generate.image`` (the guidance camera's size), or the splat
    scene rendered from the guidance camera at rest."""
    import torch

    from clflow.generate import load_image
    from clflow.media import to_uint8
    from clflow.pipeline.render import render_rgb
    from clflow.scene.load import guidance_camera, load_scene_gaussians

    camera = guidance_camera(cfg)
    if cfg.generate.image is not None:
        image = load_image(cfg.generate.image)
        if image.shape[1::-1] != (camera.width, camera.height):
            raise InputError(
                f"{cfg.source}: video.generate.image: {cfg.generate.image} is {image.shape[1]}x"
                f"{image.shape[0]} px, the guidance camera {camera.width}x{camera.height}: give the "
                f"object as the guidance camera sees it (or drop image: the scene is rendered)"
            )
        return image
    gaussians, _ = load_scene_gaussians(cfg, torch.float32)
    with torch.no_grad():
        return to_uint8(render_rgb(gaussians, camera))


def generated_path(cfg: SceneConfig, digest: str) -> Path:
    return cfg.output / CACHE_FOLDER / f"guidance-{digest[:16]}.mp4"


def ensure_guidance_video(cfg: SceneConfig, progress: Callable[[int, int], None] | None = None) -> SceneConfig:
    """``cfg`` with ``video`` set to the generated guidance video, made now unless a video
    from the same inputs (model folder, image pixels, prompt, seed, frames, fps, steps,
    guidance, size) is cached in ``output/generated/``. Configs without ``video.generate``,
    or whose video is already set, come back as they are."""
    gen = getattr(cfg, "generate", None)
    if gen is None or getattr(cfg, "video", None) is not None:
        return cfg
    import time

    from clflow.generate import check_request, generate_video, request_digest, write_generated
    from clflow.media import write_image

    fail = lambda key, message: InputError(f"{cfg.source}: video.generate{'.' + key if key else ''}: {message}")  # noqa: E731
    info = check_settings(gen, cfg.simulation, fail)
    prompt = gen.prompt if gen.prompt is not None else motion_prompt(cfg)
    resolved = check_request(info, generate_request(gen, cfg.simulation, info, prompt if info.uses_prompt else ""))
    start = time.perf_counter()
    image = guidance_image(cfg)
    digest = request_digest(info, resolved, image)
    path = generated_path(cfg, digest)
    meta = path.with_suffix(".json")
    if path.is_file() and meta.is_file():
        try:
            if parse_json(meta.read_text()).get("digest") == digest:
                log.info("guidance video: %s (generated earlier from the same inputs)", path)
                return dataclasses.replace(cfg, video=path)
        except (OSError, json.JSONDecodeError):
            pass  # a damaged record: make it again
    log.info(
        "generating the guidance video with %s (%s): %s",
        info.path.name,
        info.family.name,
        prompt if info.uses_prompt else "image only",
    )
    frames, record = generate_video(image, info, resolved.request, progress=progress)
    write_image(path.with_suffix(".input.png"), image)
    record.update(digest=digest, config=str(cfg.source), image=str(gen.image) if gen.image else "rendered scene")
    write_generated(path, frames, record, total_s=time.perf_counter() - start)
    log.info("guidance video: %s (%d frames at %g fps)", path, frames.shape[0], resolved.fps)
    return dataclasses.replace(cfg, video=path)
