"""A scene config made concrete: the splats in the simulation frame, the object's selection
and the guidance camera.

Frames: the splat file is in *scene units* with an arbitrary up axis; the simulation frame
is metres with +y up: x_sim = scale * R_up x_scene. Gaussians are moved into the simulation
frame once, at load (covariances scale by scale^2 and rotate by R_up; their SH stay in the
file's frame, so every render passes ``sh_rotations`` = R R_up). Cameras keep their
rotation and have their translation scaled: projection is scale-invariant, so pixels do
not change and depths come out in metres.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from clflow.errors import InputError
from clflow.fileio import load_arrays
from clflow.scene.config import CameraConfig, SceneConfig

if TYPE_CHECKING:
    from clflow.splat.gaussians import Gaussians


def up_rotation(up: str) -> torch.Tensor:
    """R_up [3, 3] (float64): the proper rotation taking the scene's ``up`` axis to +y."""
    sign = 1.0 if up[0] == "+" else -1.0
    axis = "xyz".index(up[1])
    if axis == 1:
        return torch.diag(torch.tensor([1.0, sign, sign], dtype=torch.float64))  # -y: turn about x
    R = torch.zeros(3, 3, dtype=torch.float64)
    if axis == 0:  # +x -> +y, +y -> -x, z fixed (for -x: +x -> -y, +y -> +x)
        R[1, 0], R[0, 1], R[2, 2] = sign, -sign, 1.0
    else:  # +z -> +y, +y -> -z, x fixed (for -z: +z -> -y, +y -> +z)
        R[1, 2], R[2, 1], R[0, 0] = sign, -sign, 1.0
    return R


def select_object(cfg: SceneConfig, means_scene: torch.Tensor) -> torch.Tensor:
    """Bool mask [N] of the objects' Gaussians (selections in scene units): all objects'."""
    return select_objects(cfg, means_scene) >= 0


def select_objects(cfg: SceneConfig, means_scene: torch.Tensor) -> torch.Tensor:
    """[N] int64: the object (its index in ``cfg.objects``) each Gaussian belongs to, -1 for
    the static ones; InputError for an object that selects no Gaussian, and for two objects
    that select the same ones (naming both and how many they share)."""
    labels = torch.full((means_scene.shape[0],), -1, dtype=torch.long)
    for k, obj in enumerate(cfg.objects):
        mask = _selection_mask(obj.selection, means_scene)
        if not bool(mask.any()):
            raise InputError(f"{cfg.source}: {obj.key}.select selects no Gaussian of {cfg.splats.name}")
        taken = mask & (labels >= 0)
        if bool(taken.any()):
            j = int(labels[taken][0])
            other, shared = cfg.objects[j], int((mask & (labels == j)).sum())
            raise InputError(
                f"{cfg.source}: objects {other.name} and {obj.name} share {shared} Gaussian(s) of "
                f"{cfg.splats.name}: each Gaussian belongs to one object; shrink {other.key}.select or {obj.key}.select"
            )
        labels[mask] = k
    return labels


def _selection_mask(sel, means_scene: torch.Tensor) -> torch.Tensor:
    """Bool mask [N] of the Gaussians a :class:`~clflow.scene.config.Selection` picks."""
    if sel.mask is not None:
        raw = next(iter(load_arrays(sel.mask, "object mask").values()), np.zeros(0))
        n = means_scene.shape[0]
        if raw.dtype == bool and raw.shape == (n,):
            return torch.from_numpy(raw)
        if np.issubdtype(raw.dtype, np.integer) and raw.ndim == 1:
            if raw.size and (raw.min() < 0 or raw.max() >= n):
                raise InputError(f"{sel.mask}: Gaussian indices must lie in [0, {n})")
            mask = torch.zeros(n, dtype=torch.bool)
            mask[torch.from_numpy(raw.astype(np.int64))] = True
            return mask
        raise InputError(f"{sel.mask}: expected {n} booleans or a list of indices, got {raw.dtype} {raw.shape}")
    if sel.ply is not None:
        return part_mask(sel.ply, means_scene, sel.tolerance)
    return sel.region.select(means_scene)


PART_TOLERANCE = 1e-5  # default match distance of a part's centres, as a fraction of the scene's diagonal


def part_mask(part_file, means_scene: torch.Tensor, tolerance: float | None = None) -> torch.Tensor:
    """Bool mask [N] of the Gaussians (centres means_scene [N, 3], scene units) that lie within
    ``tolerance`` (scene units; None: PART_TOLERANCE of the scene's diagonal, plus the
    quantisation error of a compressed part) of a Gaussian centre of ``part_file``, a PLY
    of part of the same scene (as a splat editor exports it). A part none of whose centres
    matches is an :class:`InputError`; one only some of whose centres match is logged."""
    import logging

    from scipy.spatial import cKDTree

    from clflow.splat.compressed_ply import is_compressed_ply, position_error
    from clflow.splat.ply import load_ply, require_gaussians

    part = require_gaussians(load_ply(part_file), part_file).means.double().numpy()
    scene = means_scene.double().numpy()
    if tolerance is None:
        tolerance = PART_TOLERANCE * float(np.linalg.norm(scene.max(0) - scene.min(0)))
        if is_compressed_ply(part_file):
            tolerance += position_error(part_file)
    mask = cKDTree(part).query(scene)[0] <= tolerance
    if not mask.any():
        nearest = cKDTree(scene).query(part)[0].min()
        raise InputError(
            f"{part_file}: none of its {len(part)} Gaussian centres lies within {tolerance:.3g} scene units "
            f"of the scene's (nearest {nearest:.3g}): not a part of this splat file, or moved since "
            f"(raise object.select.tolerance if it was only rounded)"
        )
    unmatched = int((cKDTree(scene[mask]).query(part)[0] > tolerance).sum())
    if unmatched:
        logging.getLogger(__name__).warning(
            "%s: %d of its %d Gaussian centres match no Gaussian of the scene within %.3g scene units",
            part_file,
            unmatched,
            len(part),
            tolerance,
        )
    return torch.from_numpy(mask)


def check_object_sizes(cfg: SceneConfig, means: torch.Tensor, scales: torch.Tensor, mask: torch.Tensor) -> None:
    """Refuse object Gaussians larger than the whole scene (std dev beyond its extent): a
    broken splat file, which would otherwise simulate and render as nonsense."""
    extent = float((means.max(0).values - means.min(0).values).norm())
    largest = scales[mask].max(-1).values
    huge = int((largest > max(extent, 1e-12)).sum())
    if huge:
        raise InputError(
            f"{cfg.splats}: {huge} of the object's {int(mask.sum())} Gaussians are larger than the "
            f"whole scene (std dev up to {float(largest.max()):.3g}, the scene spans {extent:.3g} in "
            f"scene units); check the file's scale_* values (log std devs in 3DGS files)"
        )


def load_scene_gaussians(cfg: SceneConfig, dtype: torch.dtype) -> tuple[Gaussians, torch.Tensor]:
    """All Gaussians of the splat file in the simulation frame (sh_rotations R_up), and the
    mask [N] of the objects' Gaussians."""
    gaussians, labels = load_scene_objects(cfg, dtype)
    return gaussians, labels >= 0


def load_scene_objects(cfg: SceneConfig, dtype: torch.dtype) -> tuple[Gaussians, torch.Tensor]:
    """All Gaussians of the splat file in the simulation frame (sh_rotations R_up), and each
    one's object [N] (an index into ``cfg.objects``, -1 static): :func:`select_objects`."""
    from clflow.splat.ply import load_ply, require_gaussians

    g = require_gaussians(load_ply(cfg.splats), cfg.splats)  # else "object.select selects none of them"
    labels = select_objects(cfg, g.means.double())
    check_object_sizes(cfg, g.means.double(), g.scales.double(), labels >= 0)
    return g.transformed(up_rotation(cfg.up), cfg.scale).to(dtype), labels


def to_simulation_camera(camera, cfg: SceneConfig):
    """The camera with its world frame changed from scene units to the simulation frame."""
    from clflow.splat.cameras import transform_camera

    return transform_camera(camera, _frame_change(up_rotation(cfg.up)), cfg.scale)


def _frame_change(R: torch.Tensor) -> torch.Tensor:
    """[3, 4] [R | 0] in float64."""
    return torch.cat([R.double(), torch.zeros(3, 1, dtype=torch.float64)], 1)


def to_file_frame(means, covariances, R_up, scale: float):
    """The inverse of the load: simulation-frame means [..., 3] (m) and covariances [..., 3, 3]
    (m^2) back in the splat file's frame (scene units); numpy or torch, R_up [3, 3]."""
    return means @ R_up / scale, R_up.T @ covariances @ R_up / scale**2


def to_file_camera(camera, R_up: torch.Tensor, scale: float):
    """The inverse of :func:`to_simulation_camera`: the camera with its world frame back in the
    splat file's axes and units (the same pixels)."""
    from clflow.splat.cameras import transform_camera

    return transform_camera(camera, _frame_change(R_up.T), 1.0 / scale)


def guidance_camera(cfg: SceneConfig, camera: CameraConfig | None = None):
    """The configured guidance camera (or ``camera``, another view's), in the simulation frame."""
    from clflow.splat import cameras

    cam = cfg.camera if camera is None else camera
    if cam.cameras_file is None and cam.colmap is None:
        fov_x = 2 * math.atan(math.tan(math.radians(cam.fov_y_deg) / 2) * cam.width / cam.height)  # rad
        scene_cam = cameras.look_at(
            cam.position, cam.look_at, cam.up, fov_x=fov_x, width=cam.width, height=cam.height, name="guidance"
        )
        return to_simulation_camera(scene_cam, cfg)
    loaded = file_camera(cfg, cam)
    if cfg.dataparser_transforms is not None:  # capture frame -> the splat file's
        loaded = cameras.transform_camera(loaded, *cameras.load_dataparser_transforms(cfg.dataparser_transforms))
    return to_simulation_camera(loaded, cfg)


def file_camera(cfg: SceneConfig, cam: CameraConfig):
    """The camera ``cam`` names in a camera file or COLMAP model, in that file's frame."""
    from clflow.splat import cameras

    if cam.cameras_file is not None:
        from clflow.fileio import read_text
        from clflow.fileio.reading import parse_json

        text = read_text(cam.cameras_file, "camera file")
        try:  # 3DGS cameras.json is a list; NeRF transforms.json an object with "frames"
            is_list = isinstance(parse_json(text), list)
        except ValueError as exc:
            raise InputError(f"{cam.cameras_file}: not a readable JSON camera file ({exc})") from None
        load = cameras.load_cameras_json if is_list else cameras.load_transforms_json
        loaded = load(cam.cameras_file)
        if not 0 <= cam.index < len(loaded):
            raise InputError(
                f"{cfg.source}: camera.index {cam.index} is outside the {len(loaded)} cameras of "
                f"{cam.cameras_file.name}"
            )
        return loaded[cam.index]
    return colmap_camera(cam.colmap, cam.image, cam.index, cfg.source)


def colmap_camera(folder, image: str | None, index: int, source):
    """The camera of the COLMAP sparse model in ``folder`` that took ``image`` (a file name),
    else its ``index``-th image in name order (scene units)."""
    from clflow.recon.colmap import model_cameras, read_model

    loaded = model_cameras(read_model(folder), str(folder))
    names = [c.name for c in loaded]
    if image is not None:
        if image not in names:
            listed = ", ".join(names[:5]) + (f" ... ({len(names)} images)" if len(names) > 5 else "")
            raise InputError(
                f"{source}: camera.image {image!r} is not an image of the COLMAP model {folder} ({listed})"
            )
        return loaded[names.index(image)]
    if not 0 <= index < len(loaded):
        raise InputError(
            f"{source}: camera.index {index} is outside the {len(loaded)} images of the COLMAP model {folder}"
        )
    return loaded[index]
