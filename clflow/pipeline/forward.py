"""Forward runs of a scene config: simulate the objects (no gradients), render its frames
and videos (``clflow simulate CONFIG``; per-frame Gaussians: clflow.pipeline.frames4d)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from clflow.pipeline.render import frame_gaussians, render_rgb_frames
from clflow.pipeline.simulation import ObjectSetup, ObjectValues, build_simulator, setup_object
from clflow.scene.config import SceneConfig, split_parameter
from clflow.scene.load import guidance_camera, load_scene_objects
from clflow.splat.device_scene import DeviceScene
from clflow.splat.gaussians import Gaussians

log = logging.getLogger(__name__)


@dataclass
class Prepared:
    """A config's scene, loaded once: static and object Gaussians (simulation frame; the
    objects' object by object), the objects' particles and grid, and the guidance camera."""

    cfg: SceneConfig
    static: Gaussians
    obj_rest: Gaussians
    setup: ObjectSetup
    camera: object  # clflow.splat.cameras.Camera

    @property
    def gaussian_objects(self) -> torch.Tensor:
        """[n] int64: the object (an index into ``cfg.objects``) of each of ``obj_rest``'s Gaussians."""
        n = self.obj_rest.means.shape[0]
        return torch.zeros(n, dtype=torch.long) if self.setup is None else self.setup.object_index[:n]


@dataclass
class SimulationResult:
    """A forward run of a prepared scene: its frames, and the values it ran with."""

    prepared: Prepared
    x: torch.Tensor  # [T+1, M, 3] particle positions (m)
    F: torch.Tensor  # [T+1, M, 3, 3] deformation gradients
    clamped: torch.Tensor | None = None  # [T+1] particles clamped at the grid's edge per frame
    substeps: int = 0  # substeps per frame the run used
    values: tuple = ()  # each object's clflow.pipeline.simulation.ObjectValues

    def scene_at(self, t: int) -> Gaussians:
        p = self.prepared
        return frame_gaussians(p.static, p.obj_rest, self.x[t], self.F[t])


def prepare(cfg: SceneConfig, dtype: torch.dtype = torch.float32, scene=None) -> Prepared:
    """The config's scene loaded (``scene``: what :func:`load_scene_objects` returned for it,
    else loaded here) and its particles made."""
    gaussians, labels = scene if scene is not None else load_scene_objects(cfg, dtype)
    order = torch.cat([(labels == k).nonzero().flatten() for k in range(len(cfg.objects))])  # object by object
    obj = gaussians.select(order)
    static = gaussians.select((labels < 0).nonzero().flatten())
    setup = setup_object(cfg, obj, labels[order])
    log.info(
        "%s: %d Gaussians + %d fill particles; grid %s, dx %.4g m",
        cfg.objects_label,
        setup.particles.n_gaussians,
        setup.particles.n_fill,
        setup.grid.resolution,
        setup.grid.dx,
    )
    return Prepared(cfg, static, obj, setup, guidance_camera(cfg))


def scene_values(cfg: SceneConfig, overrides: dict[str, float] | None = None) -> tuple[ObjectValues, ...]:
    """Each object's ObjectValues as the config gives them, with ``overrides`` (SI; density
    too) applied: the one object's by bare name, else by OBJECT.PARAM (an optimisation's
    values; ValueError for a name of no object)."""
    params = [dict(o.material.parameters) for o in cfg.objects]
    densities = [o.material.density for o in cfg.objects]
    for name, value in (overrides or {}).items():
        k, param = split_parameter(cfg.objects, name)
        if param == "density":
            densities[k] = float(value)
        else:
            params[k][param] = float(value)
    return tuple(ObjectValues(p, d, o.velocity) for p, d, o in zip(params, densities, cfg.objects))


def simulate_config(
    cfg: SceneConfig,
    overrides: dict[str, float] | None = None,
    prepared: Prepared | None = None,
    max_substeps: int | None = None,
    on_frame: Callable[[int], None] | None = None,
    min_substeps: int = 1,
    strict_cfl: bool = True,
) -> SimulationResult:
    """Run the config's simulation (no gradients) with its material or ``overrides``, at
    least ``min_substeps`` per frame (an optimised result's own), calling ``on_frame(k)``
    after frame k. First log the substeps and the predicted time, and refuse
    (SubstepLimitError) a run needing more substeps per frame than ``max_substeps`` (default
    ``simulation.max_substeps``). A run that breaks the CFL limit is run again at twice the
    substeps, as the optimiser does, and is an error (SimulationError) at the limit or with a
    fixed ``simulation.substep_dt``; ``strict_cfl=False`` only warns."""
    from clflow.mpm import SimulationError
    from clflow.pipeline.preflight import describe, plan_run

    prepared = prepared or prepare(cfg)
    values = scene_values(cfg, overrides)
    max_substeps = cfg.simulation.max_substeps if max_substeps is None else max_substeps
    plan = plan_run(cfg, prepared.setup, values, min_substeps=min_substeps, max_substeps=max_substeps)
    log.info("%s", describe(plan, "simulation", gradient=False))
    while True:
        sim = build_simulator(cfg, prepared.setup, values, min_substeps=min_substeps, max_substeps=max_substeps)
        try:
            traj = sim.run(cfg.simulation.frames, on_frame, strict_cfl=strict_cfl)
            break
        except SimulationError as exc:
            if "CFL" not in str(exc):
                raise
            dt = cfg.simulation.substep_dt
            if dt is not None:  # a retry would run the same substeps again
                raise SimulationError(
                    f"{exc} (simulation.substep_dt = {dt:.3g} s is fixed: a shorter one, or auto)"
                ) from None
            if 2 * sim.substeps > max_substeps:
                raise SimulationError(
                    f"{exc} (the limit is {max_substeps} substeps per frame: --max-substeps)"
                ) from None
            log.info("%s: simulating again at %d substeps per frame", exc, 2 * sim.substeps)
            min_substeps = 2 * sim.substeps
    return SimulationResult(prepared, traj.x, traj.F, traj.clamped, sim.substeps, values)


def render_frames(
    result: SimulationResult, camera=None, supersample: int = 1, scene: DeviceScene | None = None, states=None
) -> np.ndarray:
    """[T+1, H, W, 3] uint8 frames of the simulation seen by ``camera`` (default: guidance);
    ``supersample``: each pixel the area average of supersample^2 rendered ones, as a
    camera's pixel integrates light over its area. Rendered with the scene on the device
    (``scene``: the prepared scene's, made here when not given; ``states``: the run's frames
    there, clflow.mpm.Frames.states), averaged there too."""
    camera = camera or result.prepared.camera
    p = result.prepared
    scene = scene or DeviceScene(p.static, p.obj_rest)
    return render_rgb_frames(scene, result.x, result.F, camera, states=states, supersample=supersample)


def render_video(result: SimulationResult, frames_dir: Path, video: Path | None = None, camera=None) -> np.ndarray:
    """Write the frames as ``frames_dir/000.png ...`` (and ``video``, .mp4 or .gif); each file atomically."""
    from clflow.media import write_image, write_video

    frames = render_frames(result, camera)
    frames_dir.mkdir(parents=True, exist_ok=True)
    for t, frame in enumerate(frames):
        write_image(frames_dir / f"{t:03d}.png", frame)
    if video is not None:
        write_video(video, frames, result.prepared.cfg.simulation.fps)
    return frames
