"""What to generate: the request, checked against the model before anything is loaded, and
the digest of everything that makes its frames."""

from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from clflow.errors import InputError
from clflow.generate.models import ModelInfo

log = logging.getLogger("clflow.generate")

FITS = ("pad", "crop")
OUTPUT_SIZES = ("image", "model")


@dataclass(frozen=True)
class GenerateRequest:
    """What to generate; None picks the model's default."""

    prompt: str = ""
    negative_prompt: str = ""
    frames: int | None = None
    fps: float | None = None
    seed: int = 0
    steps: int | None = None
    guidance_scale: float | None = None
    size: tuple[int, int] | None = None  # (width, height) the model generates at
    fit: str = "pad"  # "pad": the whole image, padded to the model's aspect; "crop": filled, cropped
    output_size: str = "image"  # "image": frames cut and scaled back to the image's area; "model": as made
    cpu_offload: bool = False
    vae_tiling: bool = False
    vae_slicing: bool = False


@dataclass(frozen=True)
class Resolved:
    """A request with every default filled in from the model."""

    request: GenerateRequest
    frames: int
    fps: float
    steps: int
    guidance_scale: float
    size: tuple[int, int]


def parse_size(text: str) -> tuple[int, int]:
    """``"720x480"`` -> (720, 480)."""
    parts = str(text).lower().replace("×", "x").split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise InputError(f"size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 720x480")
    w, h = (int(p) for p in parts)
    if w < 1 or h < 1:
        raise InputError(f"size {text!r}: width and height must be positive")
    return w, h


def check_request(info: ModelInfo, request: GenerateRequest) -> Resolved:
    """Fill the model's defaults in and refuse what the model cannot make (frame count, size,
    a missing prompt, memory options it does not offer), before any weight is loaded."""
    where = f"{info.path.name} ({info.family.name})"
    frames = info.default_frames if request.frames is None else request.frames
    step = info.frame_step
    if frames < 2:
        raise InputError(f"frames: {where} needs at least 2 frames, got {frames}")
    if step > 1 and (frames - 1) % step:
        below = 1 + (frames - 1) // step * step
        raise InputError(
            f"frames: {where} makes 1 + k x {step} frames (what its VAE decodes): "
            f"got {frames}; use {max(below, 1 + step)} or {below + step}"
        )
    size = request.size or info.default_size
    w, h = size
    if info.fixed_size and size != info.default_size:
        raise InputError(
            f"size: {where} makes only {info.default_size[0]}x{info.default_size[1]} videos (learned "
            f"positional embeddings), got {w}x{h}; the image is fitted to that size itself"
        )
    m = info.size_multiple
    if w % m or h % m:
        raise InputError(
            f"size: {where} needs width and height that are multiples of {m}, got {w}x{h}; "
            f"e.g. {max(m, w // m * m)}x{max(m, h // m * m)}"
        )
    if info.uses_prompt and not request.prompt.strip():
        raise InputError(f"prompt: {where} needs a prompt describing the motion (--prompt)")
    if not info.uses_prompt and (request.prompt.strip() or request.negative_prompt.strip()):
        log.warning("%s takes no prompt (image only): the prompt is ignored", info.family.name)
    guidance = info.family.default_guidance if request.guidance_scale is None else request.guidance_scale
    if not (math.isfinite(guidance) and guidance >= (1.0 if not info.uses_prompt else 0.0)):
        raise InputError(
            f"guidance scale: {where} needs a finite value >= {1 if not info.uses_prompt else 0}, got {guidance}"
        )
    if not info.uses_prompt and (request.vae_tiling or request.vae_slicing):
        which = "tiling" if request.vae_tiling else "slicing"
        raise InputError(
            f"VAE {which}: {where}'s temporal VAE does not offer it (it decodes a few frames at a time already)"
        )
    fps = info.family.default_fps if request.fps is None else request.fps
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be positive, got {fps}")
    steps = info.family.default_steps if request.steps is None else request.steps
    if steps < 1:
        raise InputError(f"steps must be >= 1, got {steps}")
    if request.fit not in FITS or request.output_size not in OUTPUT_SIZES:
        raise InputError(f"fit must be one of {FITS} and output size one of {OUTPUT_SIZES}")
    return Resolved(request, frames, float(fps), steps, float(guidance), (w, h))


def request_digest(info: ModelInfo, resolved: Resolved, image: np.ndarray) -> str:
    """A hash of everything that makes the frames: the model folder's fingerprint, the image's
    pixels and the resolved request (memory options excluded: they change how, not what)."""
    req = asdict(replace(resolved.request, cpu_offload=False, vae_tiling=False, vae_slicing=False))
    payload = {
        "model": info.fingerprint(),
        "class": info.class_name,
        "request": req,
        "frames": resolved.frames,
        "fps": resolved.fps,
        "steps": resolved.steps,
        "guidance": resolved.guidance_scale,
        "size": list(resolved.size),
        "image": hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest(),
        "image_shape": list(image.shape),
        "format": 1,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()
