"""Guidance videos from an image-to-video diffusion model (Hugging Face ``diffusers``):
``clflow generate`` and the scene config's ``video: {generate: ...}`` (docs/generate.md).

    info = inspect_model("models/CogVideoX-5b-I2V")          # reads JSON only: no torch, no weights
    request = GenerateRequest(prompt="...", frames=49, seed=0)
    check_request(info, request, image_size=(512, 512))       # bad frames/size: InputError
    frames, record = generate_video(image, info, request)     # [T, H, W, 3] uint8, the JSON record
    write_generated("guidance.mp4", frames, record)            # clflow.media + guidance.json

Two model families, told apart by ``model_index.json``'s ``_class_name``:
``CogVideoXImageToVideoPipeline`` (image + prompt) and ``StableVideoDiffusionPipeline``
(image only). Models are read from a local folder in diffusers layout with
``local_files_only=True``: nothing is ever downloaded. Everything about the folder, the
image, the frame count and the size is checked before torch loads a weight.

diffusers, transformers and accelerate are the optional extra ``clflow[video]``; without them
the model folder is still checked, and loading says which extra to install.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from clflow.environment import environment
from clflow.errors import ClflowError, InputError
from clflow.limits import format_duration

log = logging.getLogger(__name__)

EXTRA = "video"
INSTALL_HINT = f"pip install 'clflow[{EXTRA}]' (from a checkout: pip install -e '.[{EXTRA}]')"
FITS = ("pad", "crop")
OUTPUT_SIZES = ("image", "model")
#: CPU throughput assumed by the up-front time estimate (FLOP/s per core, float32 matmuls);
#: the estimate is replaced by a measured one after the first denoising step.
CPU_FLOPS_PER_CORE = 20e9


@dataclass(frozen=True)
class Family:
    """What clflow knows about one diffusers image-to-video pipeline class."""

    name: str  # short name in messages
    components: dict[str, str]  # component folder -> kind: "model", "tokenizer", "scheduler", "processor"
    denoiser: str  # the component that runs every step
    uses_prompt: bool
    default_steps: int
    default_guidance: float
    default_fps: float  # the frame rate the model was trained at


FAMILIES: dict[str, Family] = {
    "CogVideoXImageToVideoPipeline": Family(
        "CogVideoX image-to-video",
        {
            "tokenizer": "tokenizer",
            "text_encoder": "model",
            "vae": "model",
            "transformer": "model",
            "scheduler": "scheduler",
        },
        "transformer",
        uses_prompt=True,
        default_steps=50,
        default_guidance=6.0,
        default_fps=8.0,
    ),
    "StableVideoDiffusionPipeline": Family(
        "Stable Video Diffusion",
        {
            "image_encoder": "model",
            "feature_extractor": "processor",
            "unet": "model",
            "vae": "model",
            "scheduler": "scheduler",
        },
        "unet",
        uses_prompt=False,
        default_steps=25,
        default_guidance=3.0,
        default_fps=7.0,
    ),
}

WEIGHT_SUFFIXES = (".safetensors", ".bin")
_CONFIG_FILES = {
    "model": ("config.json",),
    "scheduler": ("scheduler_config.json",),
    "processor": ("preprocessor_config.json",),
    "tokenizer": ("tokenizer_config.json", "tokenizer.json", "spiece.model"),
}


def expected_layout() -> str:
    """One line: the folder layouts clflow generate reads."""
    return "; ".join(
        f"{cls} ({f.name}): model_index.json and folders {', '.join(f.components)}" for cls, f in FAMILIES.items()
    )


@dataclass(frozen=True)
class ModelInfo:
    """A checked model folder: its family and the frame counts and sizes it takes."""

    path: Path
    class_name: str
    family: Family
    default_size: tuple[int, int]  # (width, height) px
    size_multiple: int  # width and height must be multiples of this
    fixed_size: bool  # learned positional embeddings: only default_size
    default_frames: int
    frame_step: int  # frames must be 1 + k * frame_step (the VAE's temporal compression)
    max_text_tokens: int  # CogVideoX: the prompt's token budget
    weight_bytes: int  # the denoiser's weight files

    @property
    def uses_prompt(self) -> bool:
        return self.family.uses_prompt

    def fingerprint(self) -> str:
        """A hash of the folder's configs and its weight files' names, sizes and times: what the
        cache of ``video: {generate: ...}`` keys on (hashing gigabytes of weights would be slow)."""
        h = hashlib.sha256()
        for p in sorted(self.path.rglob("*")):
            if p.is_file():
                rel = p.relative_to(self.path).as_posix()
                h.update(rel.encode())
                if p.suffix == ".json" and p.stat().st_size < 1 << 22:
                    h.update(p.read_bytes())
                else:
                    st = p.stat()
                    h.update(f"{st.st_size}:{st.st_mtime_ns}".encode())
        return h.hexdigest()


def _read_json(path: Path, where: str) -> dict:
    from clflow.fileio import read_json

    data = read_json(path, f"{where}: {path.name}")
    if not isinstance(data, dict):
        raise InputError(f"{where}: {path.name} must hold a JSON object")
    return data


def inspect_model(path: str | os.PathLike) -> ModelInfo:
    """Check a local diffusers model folder (JSON files and file names only: no torch) and read
    the frame counts and sizes it takes. A missing, partial or wrong-kind folder raises an
    :class:`InputError` that says what layout is expected."""
    path = Path(path).expanduser().resolve()
    if not path.exists():
        raise InputError(
            f"{path}: model folder not found (a local diffusers folder; clflow never downloads "
            f"weights). Expected: {expected_layout()}"
        )
    if not path.is_dir():
        raise InputError(
            f"{path}: not a folder; --model takes a local diffusers model folder. Expected: {expected_layout()}"
        )
    index_path = path / "model_index.json"
    if not index_path.is_file():
        raise InputError(
            f"{path}: no model_index.json, so not a diffusers pipeline folder. Expected: {expected_layout()}"
        )
    index = _read_json(index_path, str(path))
    cls = index.get("_class_name")
    family = FAMILIES.get(cls) if isinstance(cls, str) else None
    if family is None:
        raise InputError(
            f"{path}: model_index.json names {cls!r}, which clflow generate does not run "
            f"(image-to-video only). Expected: {expected_layout()}"
        )
    for name, kind in family.components.items():
        try:
            _check_component(path, name, kind, index, family)
        except InputError as exc:
            raise InputError(
                f"{exc}. Expected a {cls} folder: model_index.json and the folders "
                f"{', '.join(family.components)}, each with its config and weights"
            ) from None
    if family.name.startswith("CogVideoX"):
        return _cogvideox_info(path, cls, family)
    return _svd_info(path, cls, family)


def _check_component(root: Path, name: str, kind: str, index: dict, family: Family) -> None:
    where = f"{root}: {family.name} component {name!r}"
    if not isinstance(index.get(name), list) or index[name][1] is None:
        raise InputError(f"{where} is not listed in model_index.json (a partial or edited folder?)")
    folder = root / name
    if not folder.is_dir():
        raise InputError(f"{where}: folder {folder} is missing (a partial download or copy?)")
    if not any((folder / f).is_file() for f in _CONFIG_FILES[kind]):
        raise InputError(f"{where}: {folder} holds none of {', '.join(_CONFIG_FILES[kind])}")
    if kind == "model" and not any(p.suffix in WEIGHT_SUFFIXES for p in folder.iterdir()):
        raise InputError(f"{where}: {folder} holds no weights (*.safetensors or *.bin)")
    if kind == "model":
        for p in folder.iterdir():
            if p.name.endswith(".index.json"):  # sharded weights: every shard must be there
                shards = set(_read_json(p, where).get("weight_map", {}).values())
                missing = sorted(s for s in shards if not (folder / s).is_file())
                if missing:
                    raise InputError(f"{where}: weight shard {missing[0]} is missing ({len(missing)} of {len(shards)})")


def _weight_bytes(folder: Path) -> int:
    files = [p for p in folder.iterdir() if p.suffix in WEIGHT_SUFFIXES]
    safetensors = [p for p in files if p.suffix == ".safetensors"]
    return sum(p.stat().st_size for p in (safetensors or files))


def _cogvideox_info(path: Path, cls: str, family: Family) -> ModelInfo:
    tr = _read_json(path / "transformer" / "config.json", f"{path}: transformer")
    vae = _read_json(path / "vae" / "config.json", f"{path}: vae")
    spatial = 2 ** (len(vae.get("block_out_channels", [128, 256, 256, 512])) - 1)
    # the VAE compresses time 4x and decodes the latent frames after the first in pairs: only
    # an odd latent count decodes to the frames asked for (9 -> 3 -> 9, but 5 -> 2 -> 8), so
    # the frame counts are 1 + k * 8 (49 for CogVideoX-5b-I2V, 81 for 1.5)
    temporal = 2 * int(vae.get("temporal_compression_ratio", 4))
    patch = int(tr.get("patch_size", 2))
    return ModelInfo(
        path,
        cls,
        family,
        default_size=(int(tr.get("sample_width", 90)) * spatial, int(tr.get("sample_height", 60)) * spatial),
        size_multiple=spatial * patch,
        fixed_size=bool(tr.get("use_learned_positional_embeddings", False)),
        default_frames=int(tr.get("sample_frames", 49)),
        frame_step=temporal,
        max_text_tokens=int(tr.get("max_text_seq_length", 226)),
        weight_bytes=_weight_bytes(path / "transformer"),
    )


def _svd_info(path: Path, cls: str, family: Family) -> ModelInfo:
    unet = _read_json(path / "unet" / "config.json", f"{path}: unet")
    vae = _read_json(path / "vae" / "config.json", f"{path}: vae")
    spatial = 2 ** (len(vae.get("block_out_channels", [128, 256, 512, 512])) - 1)
    native = int(unet.get("sample_size", 96)) * spatial
    # the released SVD checkpoints (sample_size 96) were trained at 1024x576, the pipeline's default
    default = (1024, 576) if native >= 576 else (native, native)
    return ModelInfo(
        path,
        cls,
        family,
        default_size=default,
        size_multiple=math.lcm(8, spatial),
        fixed_size=False,
        default_frames=int(unet.get("num_frames", 25)),
        frame_step=1,
        max_text_tokens=0,
        weight_bytes=_weight_bytes(path / "unet"),
    )


# ---------------------------------------------------------------------------------------
# The request, checked against the model before anything is loaded


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


# ---------------------------------------------------------------------------------------
# Images in and frames out


def load_image(path: str | os.PathLike) -> np.ndarray:
    """[H, W, 3] uint8 RGB of an image file; transparency is laid over white (the renderer's
    background). A file that is not an image, or is too small, raises an InputError."""
    from clflow.media import read_image, to_uint8

    rgba = read_image(path)
    alpha = rgba[..., 3:] if rgba.shape[2] == 4 else np.float32(1)
    image = to_uint8(rgba[..., :3] * alpha + (1 - alpha))
    check_image(image, str(path))
    return image


def check_image(image: np.ndarray, where: str) -> None:
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"{where}: expected an RGB image, got an array of shape {image.shape}")
    h, w = image.shape[:2]
    if min(w, h) < 8:
        raise InputError(f"{where}: the image is {w}x{h} px; the model needs at least 8 px a side")
    if max(w, h) > 16 * min(w, h):
        raise InputError(
            f"{where}: the image is {w}x{h} px, too thin to fit a video model's frame (aspect ratio over 16)"
        )


@dataclass(frozen=True)
class Placement:
    """Where the image lies in the model's frame: ``box`` (x0, y0, x1, y1) px of the model frame
    holding image content, which is ``restored`` (w, h) px at the image's scale."""

    box: tuple[int, int, int, int]
    restored: tuple[int, int]


def fit_image(image: np.ndarray, size: tuple[int, int], fit: str = "pad") -> tuple[np.ndarray, Placement]:
    """Scale ``image`` [H, W, 3] to the model's ``size`` (w, h) keeping its aspect: ``pad``
    fits it inside and pads the rest with its edge pixels; ``crop`` fills the frame and cuts
    the overflow off, centred."""
    import cv2

    H, W = image.shape[:2]
    w, h = size
    scale = min(w / W, h / H) if fit == "pad" else max(w / W, h / H)
    sw, sh = max(1, round(W * scale)), max(1, round(H * scale))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    scaled = cv2.resize(image, (sw, sh), interpolation=interp)
    if fit == "pad":
        x0, y0 = (w - sw) // 2, (h - sh) // 2
        out = cv2.copyMakeBorder(scaled, y0, h - sh - y0, x0, w - sw - x0, cv2.BORDER_REPLICATE)
        return out, Placement((x0, y0, x0 + sw, y0 + sh), (W, H))
    x0, y0 = (sw - w) // 2, (sh - h) // 2
    out = scaled[y0 : y0 + h, x0 : x0 + w]
    return np.ascontiguousarray(out), Placement((0, 0, w, h), (max(1, round(w / scale)), max(1, round(h / scale))))


def restore_frames(frames: np.ndarray, placement: Placement) -> np.ndarray:
    """The generated frames [T, h, w, 3] cut to the image's area and scaled back to its pixels."""
    import cv2

    x0, y0, x1, y1 = placement.box
    out_w, out_h = placement.restored
    interp = cv2.INTER_AREA if out_w < x1 - x0 else cv2.INTER_CUBIC
    return np.stack(
        [cv2.resize(np.ascontiguousarray(f[y0:y1, x0:x1]), (out_w, out_h), interpolation=interp) for f in frames]
    )


# ---------------------------------------------------------------------------------------
# Running the model


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


def write_generated(path: str | os.PathLike, frames: np.ndarray, record: dict, total_s: float | None = None) -> Path:
    """Write the frames as a video (clflow.media, at ``record['fps']``) and the record as
    ``<video>.json`` beside it; returns the JSON's path."""
    from clflow.fileio import atomic_write_text
    from clflow.media import write_video

    path = Path(path)
    start = time.perf_counter()
    write_video(path, frames, record["fps"])
    record = dict(record, video=str(path.resolve()))
    record["timings"] = dict(record.get("timings", {}), write_s=round(time.perf_counter() - start, 3))
    if total_s is not None:
        record["timings"]["total_s"] = round(total_s, 3)
    meta = path.with_suffix(".json")
    atomic_write_text(meta, json.dumps(record, indent=2) + "\n")
    return meta


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
