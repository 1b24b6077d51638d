"""Rendering a simulated scene: colours of a frame, and the simulated optical flow between
two frames (differentiable in the object's positions and deformation gradients); a run's
colour frames with the scene on the device (:func:`render_rgb_frames`)."""

from __future__ import annotations

import numpy as np
import torch

from clflow.runtime.arrays import DeviceArray
from clflow.scene.deform import polar_rotations
from clflow.splat.device_scene import DeviceScene, render_frame, rgb_uint8
from clflow.splat.gaussians import Gaussians


def frame_gaussians(static: Gaussians, obj_rest: Gaussians, x: torch.Tensor, F: torch.Tensor) -> Gaussians:
    """The scene at one frame: the object's n Gaussians at particle positions x [>= n, 3] with
    deformation gradients F [>= n, 3, 3] (fill particles beyond n are ignored), then the
    static Gaussians."""
    n = obj_rest.means.shape[0]
    F = F[:n].to(obj_rest.means.dtype)
    moved = obj_rest.deformed(x[:n].to(obj_rest.means.dtype), F, polar_rotations(F))
    return Gaussians.cat([moved, static])


def _rasterize(g: Gaussians, camera, colors: torch.Tensor, **kwargs):
    """``rasterize_gaussians`` of ``g`` (its covariances) with ``colors`` [N, C] from ``camera``,
    without depth; ``kwargs`` go to it (sh_degree, background, ...)."""
    from clflow.splat.ops import rasterize_gaussians

    view = camera.viewmat, camera.K, camera.width, camera.height
    return rasterize_gaussians(
        g.means, None, None, g.opacities, colors, *view, covars=g.covariances, render_depth=False, **kwargs
    )


def render_rgb(g: Gaussians, camera, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """[H, W, 3] colours in [0, 1] (values may exceed 1 before clipping)."""
    sh_degree = g.sh_degree
    image, _, _, _ = _rasterize(
        g,
        camera,
        g.sh if g.sh is not None else g.colors,
        sh_degree=sh_degree,
        sh_rotations=g.sh_rotations if sh_degree else None,
        background=torch.tensor(background, dtype=g.means.dtype),
    )
    return image


def render_flow(g_t: Gaussians, g_t1: Gaussians, camera, normalize: bool = True):
    """Simulated optical flow [H, W, 2] (px per frame) from frame t to t+1 rendered at frame
    t's geometry, and alpha [H, W, 1]; both scenes list the same Gaussians in the same order."""
    from clflow.flow.simulated import render_simulated_flow

    view = camera.viewmat, camera.K, camera.width, camera.height
    return render_simulated_flow(g_t.means, g_t1.means, g_t.covariances, g_t.opacities, *view, normalize=normalize)


def render_object_alpha(g: Gaussians, camera) -> torch.Tensor:
    """[H, W] opacity of ``g`` alone (e.g. the object at frame 0)."""
    _, alpha, _, _ = _rasterize(g, camera, torch.ones(g.means.shape[0], 1, dtype=g.means.dtype))
    return alpha[..., 0]


def gaussian_colors(g: Gaussians, viewmat: torch.Tensor) -> torch.Tensor:
    """[N, C] colours of ``g`` seen from the camera of ``viewmat`` [4, 4]: its SH evaluated
    along each view direction (turned by its sh_rotations), as :func:`render_rgb` renders them,
    or its plain colours."""
    from clflow.splat.ops import view_directions
    from clflow.splat.sh import sh_to_rgb

    if g.sh is None:
        return g.colors
    rotations = g.sh_rotations if g.sh_degree else None
    return sh_to_rgb(g.sh_degree, g.sh, view_directions(g.means, viewmat.to(g.means.dtype), rotations))


def render_rgb_frames(
    scene: DeviceScene,
    x: torch.Tensor | None,
    F: torch.Tensor | None,
    camera,
    background=(1.0, 1.0, 1.0),
    states=None,
    supersample: int = 1,
) -> np.ndarray:
    """[T+1, H, W, 3] uint8 frames of a run x [T+1, >= n, 3], F [T+1, >= n, 3, 3] seen by
    ``camera``, rendered with the scene on the device: :func:`render_rgb` of
    :func:`frame_gaussians` per frame, where only the object's x and F go to the device and
    the frame's bytes come back (the static Gaussians' colours once a call; the object's,
    where they change, made on the device: DeviceScene.object_colors). ``states``: the run's
    states on the device, one a frame (clflow.mpm.Frames.states), read instead of x and F
    (then None will do for those).
    ``supersample``: rendered at that many times ``camera``'s pixels per side, each pixel the
    mean of its block (rgb_uint8), on the device."""
    fine = camera.scaled(supersample) if supersample > 1 else camera
    n, dtype, dev = scene.n, scene.dtype, scene.device
    with torch.no_grad():
        if states is None:
            x, F = x[:, :n].to(dtype), F[:, :n].to(dtype)
        static = gaussian_colors(scene.static, camera.viewmat).to(dtype)
        fixed = static.new_zeros(n, 3) if scene.object_colors_vary else gaussian_colors(scene.obj_rest, camera.viewmat)
        template = DeviceArray.of(dev, torch.cat([fixed.to(dtype), static]).contiguous(), "colours")
        behind = DeviceArray.of(dev, torch.tensor(background, dtype=dtype), "background")
        frames = []
        for frame in scene.frames(x, F, states):
            colors = template
            if scene.object_colors_vary:
                colors = template.clone()
                scene.object_colors(frame, fine, colors)
            image, _ = render_frame(scene, frame, colors, behind, fine)
            frames.append(rgb_uint8(scene, image, supersample))
    return np.stack(frames)
