"""Posed training images for reconstruction: cameras from a NeRF ``transforms.json``, a
COLMAP sparse model or a 3DGS ``cameras.json``, images and optional masks, checked before
any training starts.

    data = load_views("scene/images", colmap="scene/sparse/0", background=(1, 1, 1))
    train, test = data.split(holdout_every=8)     # every 8th view held out, as in 3DGS

Masks come from the images' alpha channel or from a folder of mask images with the same
file stems (white = object); masked images are composited over ``background``, as 3DGS
does with NeRF synthetic's RGBA images. Positions are in the cameras file's units (m).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from clflow.errors import InputError
from clflow.media import read_image
from clflow.splat.cameras import Camera, load_cameras_json, load_transforms_json

IMAGE_SUFFIXES = ("", ".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
CAMERA_FILES = ("transforms.json", "cameras.json")
COLMAP_FOLDERS = ("sparse/0", "sparse")


@dataclass
class View:
    """A training or held-out view: its camera and image [H, W, 3] float32 RGB in [0, 1]
    (composited over the background where a mask or alpha channel says so)."""

    camera: Camera
    image: torch.Tensor
    path: Path


@dataclass
class ViewSet:
    """All views (sorted by camera name; a sequence's frame: by camera number) and, from a
    COLMAP model, its points xyz [P, 3] (m) and colours rgb [P, 3] in [0, 1] (None otherwise)."""

    views: list[View]
    points_xyz: torch.Tensor | None = None
    points_rgb: torch.Tensor | None = None

    def split(self, holdout_every: int = 8) -> tuple[list[View], list[View]]:
        """(training views, held-out views): views 0, k, 2k, ... are held out (k =
        ``holdout_every``, 3DGS's ``llffhold``); k = 0 holds out none."""
        if holdout_every == 0:
            return list(self.views), []
        test = [v for i, v in enumerate(self.views) if i % holdout_every == 0]
        train = [v for i, v in enumerate(self.views) if i % holdout_every != 0]
        if not train:
            raise InputError(f"{len(self.views)} view(s) with every {holdout_every}th held out leave none to train on")
        return train, test


def find_cameras(images: Path) -> dict:
    """The cameras source next to ``images`` (in it or its parent): ``{"transforms": path}``,
    ``{"cameras_json": path}`` or ``{"colmap": folder}``; :class:`InputError` if none."""
    for folder in (images, images.parent):
        for name in CAMERA_FILES:
            if (folder / name).is_file():
                return {"transforms" if name == "transforms.json" else "cameras_json": folder / name}
        for sub in COLMAP_FOLDERS:
            if any((folder / sub / f"cameras{ext}").is_file() for ext in (".bin", ".txt")):
                return {"colmap": folder / sub}
    from clflow.recon.sequence import INDEX_NAME

    if (images / INDEX_NAME).is_file():
        raise InputError(f"{images}: a multi-camera sequence ({INDEX_NAME}): pick the frame to train on with --frame N")
    raise InputError(
        f"{images}: no cameras found (transforms.json, cameras.json or a COLMAP sparse/0 model in it or its parent); "
        "name them with --transforms, --cameras or --colmap"
    )


def load_views(
    images: str | os.PathLike,
    *,
    transforms: str | os.PathLike | None = None,
    colmap: str | os.PathLike | None = None,
    cameras_json: str | os.PathLike | None = None,
    masks: str | os.PathLike | None = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    frame: int | None = None,
) -> ViewSet:
    """Cameras (at most one source; found next to ``images`` when none is given), their
    images and masks, checked: every named image exists and has its camera's size, every
    mask covers something. Raises :class:`InputError` naming the file otherwise.

    With ``frame``, ``images`` is a PAC-NeRF-style multi-camera sequence (its folder or
    ``all_data.json``, :mod:`clflow.recon.sequence`) and the views are every camera's image
    of that frame."""
    from clflow.recon.colmap import model_cameras, read_model

    images = Path(images)
    given = {
        k: Path(v) for k, v in (("transforms", transforms), ("colmap", colmap), ("cameras_json", cameras_json)) if v
    }
    bg = torch.as_tensor(background, dtype=torch.float32)
    if frame is not None:
        from clflow.recon.sequence import load_sequence

        if given:
            raise InputError(f"with a frame of a sequence the cameras come from its index: drop --{next(iter(given))}")
        seq = load_sequence(images)
        seq.check_frame(frame)
        return ViewSet(
            [
                load_view(replace(c, name=paths[frame].stem), paths[frame], seq.index, masks, bg)
                for c, paths in zip(seq.cameras, seq.images)
            ]
        )  # in camera order
    if not images.is_dir():
        raise InputError(f"{images}: the image folder does not exist")
    if len(given) > 1:
        raise InputError(f"give one cameras source, not {' and '.join(given)}")
    ((kind, source),) = (given or find_cameras(images)).items()
    xyz = rgb = None
    if kind == "transforms":
        cameras = load_transforms_json(source)
    elif kind == "cameras_json":
        cameras = load_cameras_json(source)
    else:
        model = read_model(source)
        cameras = model_cameras(model, str(source))
        if len(model.points_xyz):
            xyz = torch.from_numpy(model.points_xyz).float()
            rgb = torch.from_numpy(model.points_rgb).float() / 255
    search = [images] + ([source.parent] if kind != "colmap" else [])
    views = [
        load_view(camera, _image_path(camera.name, search, source), source, masks, bg)
        for camera in sorted(cameras, key=lambda c: c.name)
    ]
    return ViewSet(views, xyz, rgb)


def load_view(
    camera: Camera, path: Path, source: Path, masks: str | os.PathLike | None, background: torch.Tensor
) -> View:
    """The view of ``camera`` from image ``path``, composited over ``background`` [3] where
    its mask (in the folder ``masks``, else its alpha channel) says; :class:`InputError`
    when the image's size is not the camera's (``source``: the cameras file, for the message)."""
    rgba = read_image(path)
    if (rgba.shape[1], rgba.shape[0]) != (camera.width, camera.height):
        raise InputError(
            f"{path}: the image is {rgba.shape[1]}x{rgba.shape[0]} px but {source.name} gives its camera "
            f"{camera.width}x{camera.height} px (one intrinsic for images of different sizes?)"
        )
    mask = _mask(path, masks, rgba)
    image = torch.from_numpy(rgba[..., :3])
    if mask is not None:
        mask = torch.from_numpy(mask)[..., None]
        image = image * mask + background * (1 - mask)
    return View(camera, image.contiguous(), path)


def _image_path(name: str, folders: list[Path], source: Path) -> Path:
    """The file a camera names: ``name`` or its last component, with or without an image
    suffix, under each folder in turn."""
    stems = dict.fromkeys([name, Path(name).name])
    for folder in folders:
        for stem in stems:
            for suffix in IMAGE_SUFFIXES:
                candidate = folder / (stem + suffix)
                if candidate.is_file():
                    return candidate
    raise InputError(f"{source}: camera {name!r} names an image that is not in {folders[0]} (tried {name}[.png|.jpg])")


def _mask(image_path: Path, masks: str | os.PathLike | None, rgba: np.ndarray) -> np.ndarray | None:
    """[H, W] float32 in [0, 1]: the mask file with the image's stem in ``masks``, else the
    alpha channel, else None; an all-zero mask raises :class:`InputError`."""
    if masks is not None:
        candidates = [Path(masks) / (image_path.stem + s) for s in IMAGE_SUFFIXES[1:]] + [Path(masks) / image_path.name]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise InputError(f"{masks}: no mask for image {image_path.name} (expected {image_path.stem}.png)")
        mask = read_image(found)[..., 0]
        if mask.shape != rgba.shape[:2]:
            raise InputError(
                f"{found}: the mask is {mask.shape[1]}x{mask.shape[0]} px, its image {rgba.shape[1]}x{rgba.shape[0]} px"
            )
        where = found
    elif rgba.shape[2] == 4:
        mask, where = rgba[..., 3], image_path
    else:
        return None
    if not mask.any():
        raise InputError(f"{where}: the mask is empty (no pixel marks the object)")
    return mask
