"""Forward runs of a scene config: simulate the object, render frames and videos, export
per-frame Gaussians (``clflow simulate CONFIG`` and ``clflow render4d``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from clflow.fileio import atomic_path
from clflow.pipeline.render import frame_gaussians, render_rgb
from clflow.pipeline.scene import SceneGaussians, guidance_camera, load_scene_gaussians
from clflow.pipeline.simulation import ObjectSetup, build_simulator, setup_object
from clflow.scene.config import SceneConfig

log = logging.getLogger(__name__)


@dataclass
class Prepared:
    """A config's scene, loaded once: static and object Gaussians (simulation frame),
    the object's particles and grid, and the guidance camera."""

    cfg: SceneConfig
    static: SceneGaussians
    obj_rest: SceneGaussians
    setup: ObjectSetup
    camera: object  # clflow.splat.cameras.Camera


@dataclass
class SimulationResult:
    prepared: Prepared
    params: dict[str, float]
    density: float
    x: torch.Tensor  # [T+1, M, 3] particle positions (m)
    F: torch.Tensor  # [T+1, M, 3, 3] deformation gradients

    def scene_at(self, t: int) -> SceneGaussians:
        p = self.prepared
        return frame_gaussians(p.static, p.obj_rest, self.x[t], self.F[t])


def prepare(cfg: SceneConfig, dtype: torch.dtype = torch.float32) -> Prepared:
    gaussians, mask = load_scene_gaussians(cfg, dtype)
    obj = gaussians.take(mask.nonzero().flatten())
    static = gaussians.take((~mask).nonzero().flatten())
    setup = setup_object(cfg, obj)
    log.info("object: %d Gaussians + %d fill particles; grid %s, dx %.4g m", setup.particles.n_gaussians,
             setup.particles.n_fill, setup.grid.resolution, setup.grid.dx)
    return Prepared(cfg, static, obj, setup, guidance_camera(cfg))


def material_values(cfg: SceneConfig, overrides: dict[str, float] | None = None) -> tuple[dict[str, float], float]:
    """(material parameters, density) of the config, with ``overrides`` (SI) applied."""
    params = dict(cfg.material.parameters)
    density = cfg.material.density
    for name, value in (overrides or {}).items():
        if name == "density":
            density = float(value)
        else:
            params[name] = float(value)
    return params, density


def simulate_config(cfg: SceneConfig, overrides: dict[str, float] | None = None,
                    prepared: Prepared | None = None) -> SimulationResult:
    """Run the config's simulation (no gradients) with its material or ``overrides``."""
    prepared = prepared or prepare(cfg)
    params, density = material_values(cfg, overrides)
    sim = build_simulator(cfg, prepared.setup, params, density)
    traj = sim.run(cfg.simulation.frames)
    return SimulationResult(prepared, params, density, traj.x, traj.F)


def to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.detach().clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def render_frames(result: SimulationResult, camera=None) -> np.ndarray:
    """[T+1, H, W, 3] uint8 frames of the simulation seen by ``camera`` (default: guidance)."""
    camera = camera or result.prepared.camera
    with torch.no_grad():
        return np.stack([to_uint8(render_rgb(result.scene_at(t), camera)) for t in range(result.x.shape[0])])


def render_video(result: SimulationResult, frames_dir: Path, video: Path | None = None, camera=None) -> np.ndarray:
    """Write the frames as ``frames_dir/000.png ...`` (and ``video``, .mp4 or .gif); each file atomically."""
    from clflow.flow.visualize import write_image, write_video

    frames = render_frames(result, camera)
    frames_dir.mkdir(parents=True, exist_ok=True)
    for t, frame in enumerate(frames):
        write_image(frames_dir / f"{t:03d}.png", frame)
    if video is not None:
        write_video(video, frames, result.prepared.cfg.simulation.fps)
    return frames


def export_gaussians(result: SimulationResult, folder: Path) -> None:
    """Per-frame Gaussians of the whole scene: ``folder/frame_000.ply ...`` (3DGS PLY, in the
    simulation frame) and ``folder/gaussians.npz`` (means [T+1, N, 3] m, covariances
    [T+1, N, 3, 3] m^2, opacities [N], sh [N, K, 3] or colors, sh_rotations [T+1, N, 3, 3])."""
    from clflow.splat.gaussians import Gaussians
    from clflow.splat.ply import save_ply

    folder.mkdir(parents=True, exist_ok=True)
    frames = [result.scene_at(t) for t in range(result.x.shape[0])]
    with atomic_path(folder / "gaussians.npz") as tmp:
        first = frames[0]
        extra = {"sh": first.sh.numpy()} if first.sh is not None else {"colors": first.colors.numpy()}
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, means=np.stack([f.means.numpy() for f in frames]),
                covariances=np.stack([f.covariances.numpy() for f in frames]),
                sh_rotations=np.stack([f.sh_rotations.numpy() for f in frames]),
                opacities=first.opacities.numpy(), fps=result.prepared.cfg.simulation.fps, **extra)
    for t, g in enumerate(frames):
        # PLY stores scales and rotations: diagonalise each deformed covariance
        variances, axes = torch.linalg.eigh(g.covariances.double())
        axes = axes * torch.sign(torch.det(axes))[:, None, None]  # proper rotations
        quats = _rotmat_to_quat(axes)
        scales = variances.clamp(min=1e-20).sqrt()
        save_ply(folder / f"frame_{t:03d}.ply", Gaussians.from_activated(
            g.means.double(), quats, scales, g.opacities.double().clamp(1e-6, 1 - 1e-6),
            sh=None if g.sh is None else g.sh.double(), colors=None if g.colors is None else g.colors.double()))


def _rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions [N, 4] of proper rotation matrices [N, 3, 3] (Shepperd's method)."""
    m = R
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = torch.stack([
        torch.stack([1 + trace, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1),
        torch.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], -1),
        torch.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]], -1),
        torch.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1], 1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1),
    ], 1)  # [N, 4 candidates, 4]; the one with the largest norm is the best conditioned
    best = cand.norm(dim=-1).argmax(dim=1)
    q = cand[torch.arange(R.shape[0]), best]
    return q / q.norm(dim=-1, keepdim=True)
