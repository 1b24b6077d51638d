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

The model folder (``models``), the request (``request``), the image in and the frames out
(``frames``) and the run of the model (``diffusion``) are modules of their own; every name is
here as well.
"""

from clflow.generate.diffusion import (
    CPU_FLOPS_PER_CORE,
    EXTRA,
    INSTALL_HINT,
    estimate_seconds,
    generate_video,
    require_extra,
)
from clflow.generate.frames import Placement, check_image, fit_image, load_image, restore_frames, write_generated
from clflow.generate.models import (
    FAMILIES,
    WEIGHT_SUFFIXES,
    Family,
    ModelInfo,
    expected_layout,
    inspect_model,
)
from clflow.generate.request import (
    FITS,
    OUTPUT_SIZES,
    GenerateRequest,
    Resolved,
    check_request,
    parse_size,
    request_digest,
)

__all__ = [
    "CPU_FLOPS_PER_CORE",
    "EXTRA",
    "FAMILIES",
    "FITS",
    "INSTALL_HINT",
    "OUTPUT_SIZES",
    "WEIGHT_SUFFIXES",
    "Family",
    "GenerateRequest",
    "ModelInfo",
    "Placement",
    "Resolved",
    "check_image",
    "check_request",
    "estimate_seconds",
    "expected_layout",
    "fit_image",
    "generate_video",
    "inspect_model",
    "load_image",
    "parse_size",
    "request_digest",
    "require_extra",
    "restore_frames",
    "write_generated",
]
