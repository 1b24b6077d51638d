"""The guidance views of an optimisation: each camera, its video at the simulation's frame
times, the video's optical flow and confidence (computed once, cached in the output
folder), and the mask where the loss is evaluated."""

from __future__ import annotations

import dataclasses
import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from clflow.errors import InputError
from clflow.fileio import atomic_path
from clflow.pipeline.forward import Prepared
from clflow.pipeline.render import render_object_alpha
from clflow.scene.config import CameraConfig, SceneConfig
from clflow.scene.load import guidance_camera

log = logging.getLogger(__name__)


def guidance_views(cfg: SceneConfig) -> list[tuple[CameraConfig, Path | None]]:
    """(camera, video) of each guidance view: view 0 is ``camera``, ``video``."""
    return [(cfg.camera, cfg.video)] + [(v.camera, v.video) for v in cfg.more_views]


def guidance_video(cfg: SceneConfig, path: Path | None, cam, frames: int):
    """The guidance video at ``path`` (a clflow.flow.video.Video) resampled to the simulation's
    frame times, checked against the simulated time and the camera ``cam``'s image size."""
    video, resampled = resampled_guidance(cfg, path, frames)
    if (resampled.width, resampled.height) != (cam.width, cam.height):
        raise InputError(
            f"{path}: frames are {resampled.width}x{resampled.height} px, the guidance camera "
            f"{cam.width}x{cam.height}; crop/resize the video (clflow.flow.video.fit_to_camera)"
        )
    return dataclasses.replace(resampled, fps=video.fps)  # fps: the source's, to compare views


def resampled_guidance(cfg: SceneConfig, path: Path | None, frames: int):
    """(the guidance video at ``path`` as read, the same at the simulation's ``frames`` + 1
    frame times); InputError when it is unreadable, too short or has a gap there."""
    from clflow.flow.video import read_video

    if path is None:
        raise InputError(f"{cfg.source}: video is required to optimise (the guidance video or image folder)")
    # a video file keeps its own frame rate; an image folder has none: frame k is at k / fps
    video = read_video(path, fps=cfg.simulation.fps if path.is_dir() else None)
    times = np.arange(frames + 1) / cfg.simulation.fps
    if video.times is not None and video.times[-1] + 1e-9 < times[-1]:
        raise InputError(
            f"{path}: the video lasts {video.times[-1]:.3g} s, the simulation "
            f"{times[-1]:.3g} s ({frames} frames at {cfg.simulation.fps:g} fps)"
        )
    return video, video.resample(times)


def cached_observed_flow(
    cfg: SceneConfig, path: Path, frames: np.ndarray, static: np.ndarray, cache: Path
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict | None]:
    """The guidance ``frames`` [T+1, H, W, 3] (the video at ``path``) stabilised over the
    ``static`` [H, W] pixels where ``flow.stabilise`` asks (clflow.flow.stabilise), their
    optical flow [T, H, W, 2] and its confidence [T, H, W], cached in ``cache``, and what the
    stabilisation removed (its record; None without one)."""
    from clflow.flow.optical_flow import observed_confidence, observed_flow
    from clflow.flow.stabilise import stabilise

    flow_cfg = cfg.flow
    key = np.array(
        [flow_cfg.method, flow_cfg.preset, flow_cfg.confidence, flow_cfg.stabilise, str(path), str(len(frames) - 1)]
    )
    record = None
    if flow_cfg.stabilise == "static":
        frames, stabilisation = stabilise(frames, static)
        record = stabilisation.record()
    try:  # the folder's check proved it clflow's; one of an older clflow, or damaged, is made again
        with np.load(cache, allow_pickle=False) as data:
            if data["key"].tolist() == key.tolist():
                return frames, data["flow"], data["confidence"], record
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        pass
    estimator = dict(preset=flow_cfg.preset, source=str(path))
    flow = observed_flow(frames, flow_cfg.method, **estimator)
    confidence = observed_confidence(frames, flow, flow_cfg.confidence, flow_cfg.method, **estimator)
    with atomic_path(cache) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, flow=flow, confidence=confidence, key=key)
    return frames, flow, confidence, record


def static_pixels(prepared: Prepared, camera) -> np.ndarray:
    """[H, W] bool: the pixels of ``camera`` that show none of the objects at rest, nor what
    lies within a twelfth of the image of them (as the loss mask grows them): the scene that
    should stay still in the guidance video (where an object moves farther, the
    stabilisation's robust fits drop it)."""
    import torch.nn.functional as nnf

    with torch.no_grad():
        alpha = render_object_alpha(prepared.obj_rest, camera)
    grow = max(2, min(camera.width, camera.height) // 12)
    near = nnf.max_pool2d((alpha > 0.05).float()[None, None], 2 * grow + 1, stride=1, padding=grow)[0, 0] > 0
    return ~near.numpy()


def observed_flow_cache(cfg: SceneConfig, view: int) -> Path:
    """Where the observed flow of guidance view ``view`` is cached."""
    return cfg.output / ("observed_flow.npz" if view == 0 else f"observed_flow_{view}.npz")


def loss_mask(cfg: SceneConfig, prepared: Prepared, camera=None, what: str = "the guidance camera") -> torch.Tensor:
    """[H, W] bool: where the flow loss of the guidance camera (or ``camera``, named ``what``) is evaluated."""
    import torch.nn.functional as nnf

    cam = prepared.camera if camera is None else camera
    setting = cfg.flow.mask
    if setting == "none":
        return torch.ones(cam.height, cam.width, dtype=torch.bool)
    if setting == "alpha":  # the object at rest, grown so the moving object stays inside
        with torch.no_grad():
            alpha = render_object_alpha(prepared.obj_rest, cam)
        grow = max(2, min(cam.width, cam.height) // 12)
        grown = nnf.max_pool2d((alpha > 0.5).float()[None, None], 2 * grow + 1, stride=1, padding=grow)[0, 0] > 0
        if not bool(grown.any()):
            raise InputError(f"{cfg.source}: the object is not visible from {what} (empty flow mask)")
        return grown
    from clflow.flow.optical_flow import mask_from_image

    return torch.from_numpy(mask_from_image(setting, cam.width, cam.height))  # a path resolved by the config


@dataclass
class View:
    """One guidance view: its camera (simulation frame), observed flow [T, H, W, 2], loss
    weight [T, H, W] (mask x confidence), loss mask [H, W], video frames [T+1, H, W, 3] (as
    the flow saw them: stabilised where ``flow.stabilise`` asks) and what the stabilisation
    removed (clflow.flow.stabilise.Stabilisation.record; None without one)."""

    camera: object  # clflow.splat.cameras.Camera
    observed: torch.Tensor
    weight: torch.Tensor
    mask: torch.Tensor
    video_frames: np.ndarray
    stabilisation: dict | None = None


def guidance_views_of(cfg: SceneConfig, prepared: Prepared, frames: int) -> list[View]:
    """Every guidance view, its videos and masks checked before any optical flow is computed."""
    several = len(cfg.more_views) > 0
    cameras = [prepared.camera] + [guidance_camera(cfg, v.camera) for v in cfg.more_views]
    paths = [path for _, path in guidance_views(cfg)]
    videos = [guidance_video(cfg, path, cam, frames) for path, cam in zip(paths, cameras)]
    rates = [video.fps for video in videos if video.fps]  # an image folder's is simulation.fps
    if rates and max(rates) > 1.001 * min(rates):
        raise InputError(
            f"{cfg.source}: the guidance videos have different frame rates "
            f"({', '.join(f'{v.fps:g}' if v.fps else 'variable' for v in videos)} fps): give "
            f"views recorded at one rate"
        )
    masks = [
        loss_mask(cfg, prepared, cam, f"guidance camera {i}" if several else "the guidance camera")
        for i, cam in enumerate(cameras)
    ]
    views = []
    for i, (cam, path, video, mask) in enumerate(zip(cameras, paths, videos, masks)):
        static = static_pixels(prepared, cam)
        frames, flow, confidence, stabilised = cached_observed_flow(
            cfg, path, video.frames, static, observed_flow_cache(cfg, i)
        )
        if stabilised is not None and stabilised["note"]:
            log.info("guidance view %d: %s", i, stabilised["note"])
        if stabilised is not None and stabilised["frames_changed"]:
            log.info(
                "guidance view %d stabilised: %d of %d frames registered to the first (camera motion up to %.2f px, "
                "exposure up to %.1f grey levels removed)",
                i,
                stabilised["frames_changed"],
                stabilised["frames"],
                stabilised["motion_removed_px"]["max"],
                stabilised["exposure_removed_grey_levels"],
            )
        weight = mask * torch.from_numpy(confidence).double()  # [T, H, W] in [0, 1]
        views.append(View(cam, torch.from_numpy(flow).double(), weight, mask, frames, stabilised))
    return views
