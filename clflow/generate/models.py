"""The model folders ``clflow generate`` reads: a local diffusers image-to-video pipeline,
checked from its JSON files and file names alone (no torch), and the frame counts and sizes
it takes."""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

from clflow.errors import InputError


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
