"""``clflow optimize``: material parameters from a guidance video's optical flow.

Each iteration: simulate (differentiable MPM) -> render the simulated flow from the guidance
camera -> masked flow loss against the video's flow -> adjoint -> one Adam step on the
parameters' unconstrained variables z (log10 for moduli, bounded maps for ratios: see
clflow.mpm.parameterization) with a cosine-decaying rate. The loss may cover only the first
frames at first (``optimize.horizon``): a short horizon keeps the loss monotone far from the
optimum, where a long one has local minima (docs/pipeline.md). With
``optimize.estimate_velocity`` a velocity phase comes first: only the object's initial
velocity is optimised, over the first frames, with the material at its initial guess; the
main phase starts from that estimate. Adam is written out here in float64 so that its whole
state goes into ``checkpoint.json`` after every iteration; ``resume`` continues from it and
gives the same result as an uninterrupted run. A failed iteration (NaN, a simulation that blows
up, breaks the CFL limit, clamps particles at the grid's edge or needs more substeps than
``simulation.max_substeps``) is never accepted: it rolls back to the last good parameters,
halves the step and tries again (``rollbacks`` in metrics.json), or stops with the reason.
Before the first iteration the pre-flight checks (clflow.pipeline.preflight) print the
substeps and the predicted time, and refuse a run beyond the substep limit or a guidance
video that does not fit the scene (``force_video``: warn and record it instead).

Results in ``output/``: params.json, metrics.json, history.json, loss.png, comparison.mp4,
observed_flow.npz (the video's flow and its confidence, computed once).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from clflow.errors import ClflowError, InputError
from clflow.fileio import atomic_path, atomic_write_text
from clflow.mpm.parameterization import clip_factor
from clflow.pipeline.forward import Prepared, SimulationResult, material_values, prepare, render_frames
from clflow.pipeline.generated_video import ensure_guidance_video
from clflow.pipeline.material import resolve_material
from clflow.pipeline.plots import write_history_plot
from clflow.pipeline.render import frame_gaussians, render_flow, render_object_alpha
from clflow.pipeline.simulation import build_simulator, run
from clflow.scene.config import VELOCITY, VELOCITY_COMPONENTS, CameraConfig, SceneConfig
from clflow.scene.load import guidance_camera

log = logging.getLogger(__name__)

BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
# per iteration, in z units: a decade per 10 steps for log parameters, a fortieth of the
# typical range (nu 0.012, phi 1.1 deg) near its middle for bounded ones
DEFAULT_RATE = 0.1
DEFAULT_VELOCITY_RATE = 0.1  # m/s per iteration for each velocity component
MAX_FAILURES = 4  # consecutive failed iterations before giving up
CLIP_NORM = 10.0  # gradient clipping in z space
# Levenberg-Marquardt (optimize.method: levenberg_marquardt)
LM_STEP = 0.01  # finite-difference step in z (a 2.3 % change of a log-scale parameter)
LM_DAMPING = 1e-2  # initial damping (relative to the diagonal of J^T J)
LM_MAX_STEP = 1.0  # longest step in z (a decade of a log-scale parameter)
LM_TOLERANCE = 1e-3  # converged when an accepted step moves every variable less (0.23 % of a log-scale one)
LM_GAIN_TOLERANCE = 1e-3  # ... or when the Gauss-Newton model promises less than this fraction of the loss
# identifiability: a variable is weakly constrained beyond this standard error in z (a factor
# 1.26 of a log-scale parameter), two trade off beyond this correlation
WEAK_STD_Z = 0.1
TRADE_OFF_CORRELATION = 0.95
# ... or when such a step (the others refitted) raises the loss by less than this fraction: the
# standard errors treat pixels as independent noise, but what remains at the optimum is mostly
# model error (the grid, the estimator), which moves the minimum by more than that
MIN_LOSS_RISE = 0.01
# a weakly constrained material parameter is moved alone PROFILE_STEP either way in z (a
# decade of a log-scale parameter, cut to its box); it is unresolved over that range when
# neither move changes the loss by PROFILE_RISE of itself (the cream's viscosity: under 1 %
# from 1 to 10 Pa s)
PROFILE_STEP = 1.0
PROFILE_RISE = 0.1
# the grid check reruns the final point on the search grid (without a coarser search grid, on
# one GRID_CHECK_RATIO times coarser) and moves the best fit by the residuals' change: a
# variable whose fit moves more than WEAK_STD_Z is grid-sensitive (the full droplet's bulk
# modulus: 0.42 decades from 51 to 76 nodes, where it ended at 0.35 of its truth; the bird's
# E: 0.001 decades, RE 0.05; docs/benchmarks.md, "The bulk modulus sits below the model error")
GRID_CHECK_RATIO = 1.5
# flow.bias_correction renders the simulation at this many times the guidance camera's pixels
# per side and area-averages them, since a camera's pixel integrates light over its area
# (DIS's error depends on that blur: docs/flow.md)
SUPERSAMPLE = 2


@dataclass
class OptimizerState:
    """Everything needed to continue an optimisation exactly (saved as JSON, exact floats)."""

    iteration: int
    z: dict[str, float]
    m: dict[str, float]
    v: dict[str, float]
    step_scale: float = 1.0
    history: list[dict] = field(default_factory=list)
    momentum_steps: int = 0  # gradients in m since its last restart (for Adam's bias correction)
    # substeps per frame at least (automatic substeps) of the next run: Adam's never fewer than
    # an earlier iteration needed, so the loss stays one smooth function of the parameters
    # instead of jumping where a NaN/CFL retry would change dt; Levenberg-Marquardt's those
    # of its best point, from which each step is taken
    substeps: int = 1
    # the global phase's samples so far ({"z", "params", "loss", "seconds"}; loss None where
    # the simulation failed) and whether it is over (its best point is then z)
    search: list[dict] = field(default_factory=list)
    searched: bool = False
    # Levenberg-Marquardt: damping, and the best point so far (its z, loss and horizon)
    damping: float = LM_DAMPING
    best: dict | None = None
    # every iteration that failed or was unstable and was rolled back: {"iteration", "phase",
    # "reason", "params" (the rejected point), "back_to" (the last good parameters)}
    rollbacks: list[dict] = field(default_factory=list)
    # flow.bias_correction: the point whose simulation measured the flow estimator's error
    # (its z, frames and grid nodes; the error itself is saved beside the checkpoint), None before any
    calibrated_at: dict | None = None
    converged: bool = False  # Levenberg-Marquardt: no step from the best point promises progress
    # optimize.search.starts: the best search samples' z, each polished by a few Levenberg-Marquardt
    # iterations in turn, and per polished start its best point {"z", "loss", "params"}, the
    # substeps its polish ended with ("substeps": the best point's, or 1 after a step from it)
    # and, with a coarser search grid, its "model_loss" on the main phase's grid
    starts: list[dict] = field(default_factory=list)
    polished: list[dict] = field(default_factory=list)


class UnstableRun(ClflowError):
    """A simulation finished but is not to be trusted (CFL broken, particles clamped at the
    grid's edge): the optimiser rejects it like a NaN."""


@dataclass
class Evaluation:
    """The loss at one point: value, dloss/dz per parameter, simulated flows [H, W, 2] per
    frame step, the simulation (x [T+1, M, 3], F [T+1, M, 3, 3], substeps per frame) and the
    grid it ran on (nodes along the domain's longest side)."""

    loss: float
    grads: dict[str, float]
    flows: list[torch.Tensor]
    trajectory: "Frames"  # noqa: F821  (clflow.mpm.autograd.Frames)
    grid: int
    more_flows: tuple[list[torch.Tensor], ...] = ()  # the flows seen by views 1.. (several guidance views)

    @property
    def substeps(self) -> int:
        return self.trajectory.substeps


def _parameterizations(cfg: SceneConfig):
    """Material parameter name -> its parameterisation, for each of optimize.parameters
    but velocity."""
    from clflow.mpm.parameterization import parameterization

    names = cfg.optimize.parameters
    if not names:
        raise InputError(f"{cfg.source}: optimize.parameters is empty: name the parameters to optimise")
    return {name: parameterization(cfg.material.type, name) for name in names if name != VELOCITY}


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
    cfg: SceneConfig, path: Path, frames: np.ndarray, cache: Path
) -> tuple[np.ndarray, np.ndarray]:
    """Optical flow [T, H, W, 2] of ``frames`` [T+1, H, W, 3] (the video at ``path``) and its
    confidence [T, H, W], cached in ``cache``."""
    from clflow.flow.optical_flow import observed_confidence, observed_flow

    key = np.array([cfg.flow.method, cfg.flow.preset, cfg.flow.confidence, str(path), str(len(frames) - 1)])
    if cache.exists():
        with np.load(cache) as data:
            if data["key"].tolist() == key.tolist():
                return data["flow"], data["confidence"]
    estimator = dict(preset=cfg.flow.preset, source=str(path))
    flow = observed_flow(frames, cfg.flow.method, **estimator)
    confidence = observed_confidence(frames, flow, cfg.flow.confidence, cfg.flow.method, **estimator)
    with atomic_path(cache) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, flow=flow, confidence=confidence, key=key)
    return flow, confidence


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


def simulated_view_flows(
    prepared: Prepared, x: torch.Tensor, F: torch.Tensor, frames: int, cameras: list
) -> list[list[torch.Tensor]]:
    """Simulated flows [H, W, 2] of each frame step t -> t+1 (t < frames) seen by each of ``cameras``."""
    scenes = [frame_gaussians(prepared.static, prepared.obj_rest, x[t], F[t]) for t in range(frames + 1)]
    return [[render_flow(scenes[t], scenes[t + 1], cam)[0] for t in range(frames)] for cam in cameras]


def flow_loss(cfg: SceneConfig, flows, observed: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """The ``flow.loss`` of the simulated flows (T of [H, W, 2]) against ``observed``
    [T, H, W, 2], weighted per pixel by ``weight`` [T, H, W] (the loss mask times the observed
    flow's confidence) and divided by the weight's sum: a weighted per-pixel mean."""
    from clflow.flow.losses import charbonnier_flow_loss, masked_flow_loss

    fn = masked_flow_loss if cfg.flow.loss == "l2" else charbonnier_flow_loss
    return fn(torch.stack(flows).double(), observed, weight)


def phase_of(opt, iteration: int) -> tuple[str, int, int]:
    """(phase, iteration within it, its iterations) of overall ``iteration``: "velocity"
    (``optimize.estimate_velocity``) comes first, then "main"."""
    if iteration < opt.estimate_velocity_iterations:
        return "velocity", iteration, opt.estimate_velocity_iterations
    return "main", iteration - opt.estimate_velocity_iterations, opt.iterations


def horizon(cfg: SceneConfig, iteration: int) -> int:
    """Frames in the loss at ``iteration`` of the main phase (the horizon curriculum: first
    frames first)."""
    total, opt = cfg.simulation.frames, cfg.optimize
    if opt.horizon_start <= 0:
        return total
    return min(total, opt.horizon_start + opt.horizon_step * iteration)


def rate_schedule(opt, iteration: int, iterations: int | None = None) -> float:
    """Factor on the learning rates at ``iteration`` of a phase of ``iterations`` (default
    ``optimize.iterations``): cosine from 1 down to ``optimize.final_rate`` at its last
    iteration (large steps far from the optimum, small ones to settle in it)."""
    progress = iteration / max(1, (opt.iterations if iterations is None else iterations) - 1)
    return opt.final_rate + (1.0 - opt.final_rate) * 0.5 * (1.0 + math.cos(math.pi * progress))


def _by_content(value):
    """``value`` (a config field as asdict gives it) with every path replaced by the digest
    of what it holds (clflow.fileio.content_digest)."""
    from clflow.fileio import content_digest

    if isinstance(value, Path):
        return content_digest(value)
    if isinstance(value, dict):
        return {k: _by_content(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_by_content(v) for v in value]
    return value


def config_digests(cfg: SceneConfig, by_path: bool = False) -> dict[str, str]:
    """A SHA-256 of each top-level field of the resolved config (canonical JSON; files and
    folders by their contents, so a moved run resumes; ``by_path``: by their paths, as
    checkpoints before that were saved), except ``output`` and ``optimize.iterations``
    (``--resume --iterations N`` extends a run): what a resumed run must share with its
    checkpoint."""
    import hashlib

    fields = asdict(cfg)
    fields.pop("output", None)
    fields["optimize"].pop("iterations", None)
    fields["simulation"].pop("max_substeps", None)  # a run stopped by the limit may resume with a higher one
    if not fields["more_views"]:  # one view: the digests of checkpoints from before several views
        fields.pop("more_views")
    if fields.get("generate") is None:  # no generated video: the digests of checkpoints from before it
        fields.pop("generate", None)
    if not by_path:
        fields = _by_content(fields)
    return {
        name: hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()[:16]
        for name, value in fields.items()
    }


@dataclass
class View:
    """One guidance view: its camera (simulation frame), observed flow [T, H, W, 2], loss
    weight [T, H, W] (mask x confidence), loss mask [H, W], video frames [T+1, H, W, 3] and
    the flow estimator's own error [T, H, W, 2] on the simulation's rendered video
    (``flow.bias_correction``; zero until the first calibration)."""

    camera: object  # clflow.splat.cameras.Camera
    observed: torch.Tensor
    weight: torch.Tensor
    mask: torch.Tensor
    video_frames: np.ndarray
    estimator_error: torch.Tensor | None = None

    @property
    def target(self) -> torch.Tensor:
        """[T, H, W, 2] what the simulated flow is fitted to: the observed flow less the
        estimator's error measured on the simulation (the observed flow itself before any)."""
        return self.observed if self.estimator_error is None else self.observed - self.estimator_error


def flat(profile_row: dict) -> bool:
    """Whether a :meth:`Optimization.profile` row shows a loss that, moved either way, changed
    by at most PROFILE_RISE of itself (a fall is no flatter than a rise: the point is then
    not a minimum along that parameter)."""
    ratios = profile_row["loss_ratio"]
    return len(ratios) > 1 and all(r is not None and abs(r - 1) <= PROFILE_RISE for r in ratios)


class Optimization:
    """One optimisation run of a config (see module docstring)."""

    def __init__(
        self,
        cfg: SceneConfig,
        *,
        progress: Callable[[dict], None] | None = None,
        hypotheses: dict | None = None,
        force_video: bool = False,
    ):
        self.cfg = cfg = ensure_guidance_video(resolve_material(cfg))  # video: {generate: ...} made first
        self.hypotheses = hypotheses  # how the material was chosen (clflow.pipeline.hypotheses), for metrics
        self.params = _parameterizations(cfg)
        opt = cfg.optimize
        optimised = VELOCITY_COMPONENTS if VELOCITY in opt.parameters else ()
        estimated = VELOCITY_COMPONENTS if opt.estimate_velocity_iterations and not optimised else ()
        self.main_variables = tuple(self.params) + optimised  # z names the main phase optimises
        self.variables = self.main_variables + estimated  # every z name
        # every start but the kept one spends search.start_iterations iterations of its own
        extra_start_iterations = (opt.search.starts - 1) * opt.search.start_iterations if opt.search else 0
        self.total_iterations = opt.estimate_velocity_iterations + opt.iterations + extra_start_iterations
        self.progress = progress or (lambda row: None)
        self.prepared = prepare(cfg)
        # optimize.search.grid_resolution: the global phase's coarser grid over the same domain
        self.model_grid = cfg.simulation.grid_resolution
        self.search_grid = (opt.search.grid_resolution if opt.search else 0) or self.model_grid
        self._prepared = {self.model_grid: self.prepared}
        self.prepared_on(self.search_grid)
        self.frames = cfg.simulation.frames
        self.preflight()  # before the optical flow: refuse a run beyond the substep limit in seconds
        self.views = self._views()
        self.guidance_warnings = self.check_guidance(force_video)
        self.checkpoint = cfg.output / "checkpoint.json"
        self.estimator_error_file = cfg.output / "estimator_error.npz"  # a start's polish: its own
        # polishes every search start (records of Optimization.polish, in start order): one after
        # another here, or as Ray tasks (starts_on_ray: optimize --parallel)
        self.map_starts: Callable[..., list[dict]] = serial_starts
        # (z, frames, variables, substeps) -> (Evaluation, J) of the last two Jacobians: the best
        # point's and the last step's, so that a rejected step goes back without new runs
        self._lm_cache: dict[tuple, tuple[Evaluation, torch.Tensor]] = {}

    def __getstate__(self) -> dict:
        """What a Ray task gets (clflow.sweep): no progress callback or cached runs, starts polished in place."""
        return {**self.__dict__, "progress": _quiet, "map_starts": serial_starts, "_lm_cache": {}}

    def _views(self) -> list[View]:
        """Every guidance view, its videos and masks checked before any optical flow is computed."""
        cfg, several = self.cfg, len(self.cfg.more_views) > 0
        cameras = [self.prepared.camera] + [guidance_camera(cfg, v.camera) for v in cfg.more_views]
        paths = [path for _, path in guidance_views(cfg)]
        videos = [guidance_video(cfg, path, cam, self.frames) for path, cam in zip(paths, cameras)]
        rates = [video.fps for video in videos if video.fps]  # an image folder's is simulation.fps
        if rates and max(rates) > 1.001 * min(rates):
            raise InputError(
                f"{cfg.source}: the guidance videos have different frame rates "
                f"({', '.join(f'{v.fps:g}' if v.fps else 'variable' for v in videos)} fps): give "
                f"views recorded at one rate"
            )
        masks = [
            loss_mask(cfg, self.prepared, cam, f"guidance camera {i}" if several else "the guidance camera")
            for i, cam in enumerate(cameras)
        ]
        views = []
        for i, (cam, path, video, mask) in enumerate(zip(cameras, paths, videos, masks)):
            flow, confidence = cached_observed_flow(cfg, path, video.frames, observed_flow_cache(cfg, i))
            weight = mask * torch.from_numpy(confidence).double()  # [T, H, W] in [0, 1]
            views.append(View(cam, torch.from_numpy(flow).double(), weight, mask, video.frames))
        return views

    def preflight(self):
        """Force stages and the substeps at the initial parameters: the predicted time is
        logged, a run beyond ``simulation.max_substeps`` refused (SubstepLimitError)."""
        from clflow.pipeline.preflight import describe, plan_run

        z = self.initial_state().z  # plan_run builds the simulator, which checks the force stages
        values = self.values(z)
        params, density = material_values(self.cfg, {n: values[n] for n in self.params})
        plan = plan_run(
            self.cfg,
            self.prepared.setup,
            params,
            density,
            velocity=torch.tensor(self.velocity(z)),
            max_substeps=self.cfg.simulation.max_substeps,
            optimizing=True,
        )
        plan = dataclasses.replace(plan, render_seconds_per_frame=self.render_seconds())
        log.info("%s", describe(plan, "optimize", gradient=True))
        return plan

    def render_seconds(self) -> float:
        """Seconds one frame step's flow takes in every view, rendered and its gradient back
        (timed once in the guidance view on the scene at rest: what an iteration adds to the
        simulation's time)."""
        p = self.prepared
        x = p.setup.particles.positions.to(p.obj_rest.means.dtype).clone().requires_grad_()
        F = torch.eye(3, dtype=x.dtype).expand(x.shape[0], 3, 3)
        seconds = []
        for _ in range(2):  # the first builds the rasteriser's kernels
            started = time.perf_counter()
            scene = frame_gaussians(p.static, p.obj_rest, x, F)
            render_flow(scene, scene, p.camera)[0].sum().backward()
            seconds.append(time.perf_counter() - started)
        return seconds[-1] * (1 + len(self.cfg.more_views))

    def check_guidance(self, force: bool) -> list[str]:
        """The guidance checks of every view (clflow.pipeline.preflight.check_guidance): their
        problems when forced, else InputError on any."""
        from clflow.pipeline.preflight import AGREEMENT_FRAMES, check_guidance, flow_agreement, measure_view

        # inside the mask the weight is the observed flow's confidence
        self.guidance = [
            measure_view(
                self.prepared, view.camera, view.mask, view.video_frames, view.observed.numpy(), view.weight.numpy()
            )
            for view in self.views
        ]
        if VELOCITY_COMPONENTS[0] not in self.variables:  # else the start's velocity may be anything
            try:
                start = self.evaluate(self.initial_state().z, min(AGREEMENT_FRAMES, self.frames), with_grad=False)
            except (FloatingPointError, ClflowError) as exc:  # the first iteration will say so
                log.info("no flow-direction check: the start's simulation fails (%s)", exc)
            else:
                self.guidance = [
                    dataclasses.replace(check, agreement=flow_agreement(flows, view.observed, view.weight))
                    for check, view, flows in zip(self.guidance, self.views, [start.flows, *start.more_flows])
                ]
        return check_guidance(self.cfg, self.guidance, force)

    # -- state ---------------------------------------------------------------------------

    def initial_state(self) -> OptimizerState:
        values, density = material_values(self.cfg)
        values["density"] = density
        z = {n: float(p.encode(values[n])) for n, p in self.params.items()}
        if VELOCITY_COMPONENTS[0] in self.variables:
            z.update(zip(VELOCITY_COMPONENTS, self.cfg.velocity))
        return OptimizerState(0, z, {n: 0.0 for n in z}, {n: 0.0 for n in z})

    def load_state(self) -> OptimizerState:
        try:
            data = json.loads(self.checkpoint.read_text())
            state = OptimizerState(**data["state"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"cannot resume from {self.checkpoint}: {exc}") from None
        if set(state.z) != set(self.variables):
            raise InputError(f"{self.checkpoint} optimises {sorted(state.z)}, the config {sorted(self.variables)}")
        saved = data.get("config_digests")  # absent in checkpoints of older versions
        digests = config_digests(self.cfg)
        if isinstance(saved, dict) and saved != digests and saved != config_digests(self.cfg, by_path=True):
            changed = sorted(k for k in saved.keys() | digests.keys() if saved.get(k) != digests.get(k))
            raise InputError(
                f"cannot resume from {self.checkpoint}: the config changed since it was saved "
                f"({', '.join(changed)}); give another -o/--out, or delete the checkpoint to start over"
            )
        if state.calibrated_at is not None:
            self.restore_calibration(state)
        return state

    def save_state(self, state: OptimizerState, path: Path | None = None, **extra) -> None:
        """``state`` into the checkpoint (or ``path``, with ``extra`` entries)."""
        atomic_write_text(
            path or self.checkpoint,
            json.dumps(
                {
                    "config": str(self.cfg.source),
                    "state": asdict(state),
                    "config_digests": config_digests(self.cfg),
                    **extra,
                }
            ),
        )

    def prepared_on(self, grid: int) -> Prepared:
        """The scene prepared on a grid of ``grid`` nodes over the same domain (the model's,
        the search's, the grid check's), made on first use."""
        if grid not in self._prepared:
            simulation = dataclasses.replace(self.cfg.simulation, grid_resolution=grid)
            self._prepared[grid] = prepare(dataclasses.replace(self.cfg, simulation=simulation))
        return self._prepared[grid]

    def values(self, z: dict[str, float]) -> dict[str, float]:
        """The value of every variable in z: material parameters in SI, velocity components in m/s."""
        out = {n: float(p.decode(torch.tensor(z[n], dtype=torch.float64))) for n, p in self.params.items()}
        out.update((n, z[n]) for n in VELOCITY_COMPONENTS if n in z)
        return out

    def velocity(self, z: dict[str, float]) -> tuple[float, float, float]:
        """The object's initial velocity (m/s, simulation frame) at z."""
        return tuple(z[n] for n in VELOCITY_COMPONENTS) if VELOCITY_COMPONENTS[0] in z else self.cfg.velocity

    # -- one iteration -------------------------------------------------------------------

    def evaluate(
        self,
        z: dict[str, float],
        frames: int,
        with_grad: bool = True,
        min_substeps: int = 1,
        variables: tuple[str, ...] | None = None,
        grid: int | None = None,
    ) -> Evaluation:
        """Loss (and dloss/dz of ``variables``, default every z name) at z over ``frames``
        frames, simulated on the grid of ``grid`` nodes (the model's or the search's; None:
        the model's)."""
        variables = self.variables if variables is None else variables
        grid = self.model_grid if grid is None else grid
        prepared = self.prepared_on(grid)
        zt = {n: torch.tensor(v, dtype=torch.float64, requires_grad=with_grad and n in variables) for n, v in z.items()}
        decoded = {n: p.decode(zt[n]) for n, p in self.params.items()}
        params, density = material_values(self.cfg, {n: float(v.detach()) for n, v in decoded.items()})
        velocity = torch.stack([zt[n] for n in VELOCITY_COMPONENTS]) if VELOCITY_COMPONENTS[0] in zt else None
        sim = build_simulator(
            self.cfg,
            prepared.setup,
            params,
            density,
            min_substeps=min_substeps,
            velocity=velocity,
            max_substeps=self.cfg.simulation.max_substeps,
        )
        traj = run(sim, frames, decoded, velocity)
        needed = sim.stable_substeps()
        if traj.substeps < needed:  # a fixed simulation.substep_dt too long for these parameters
            raise UnstableRun(
                f"dt = {sim.frame_dt / traj.substeps:.3g} s exceeds the stable step "
                f"{sim.frame_dt / needed:.3g} s of these parameters ({sim.limit_reason(sim.state.v)})"
            )
        if traj.unstable:  # finished, but not a run to learn from
            raise UnstableRun(traj.unstable)
        cameras = [v.camera for v in self.views]
        flows, *more_flows = simulated_view_flows(prepared, traj.x, traj.F, frames, cameras)
        loss = self.loss_of([flows, *more_flows])
        if not bool(torch.isfinite(loss.detach())):
            raise FloatingPointError("the flow loss is not finite")
        grads = {}
        if with_grad:
            loss.backward()
            grads = {n: float(zt[n].grad) for n in variables}
            if not all(math.isfinite(g) for g in grads.values()):
                raise FloatingPointError("the gradient is not finite")
        return Evaluation(
            float(loss.detach()),
            grads,
            [f.detach() for f in flows],
            traj,
            grid,
            tuple([f.detach() for f in view] for view in more_flows),
        )

    # -- the flow estimator's bias ----------------------------------------------------------

    def estimator_errors(self, result: Evaluation, frames: int) -> list[torch.Tensor]:
        """The flow estimator's error [frames, H, W, 2] in each guidance view on the simulation
        ``result`` (its first ``frames`` frames): the simulation rendered from the view's camera
        (SUPERSAMPLE^2 samples per pixel, area-averaged), its flow estimated with the settings
        that made the observed flow, less the exact simulated flow."""
        from clflow.flow.optical_flow import observed_flow

        traj = result.trajectory
        simulated = SimulationResult(
            self.prepared, {}, 0.0, traj.x[: frames + 1].detach(), traj.F[: frames + 1].detach()
        )
        errors = []
        for view, flows in zip(self.views, [result.flows, *result.more_flows]):
            video = render_frames(simulated, view.camera, supersample=SUPERSAMPLE)
            estimated = observed_flow(video, self.cfg.flow.method, preset=self.cfg.flow.preset, source="the simulation")
            errors.append(torch.from_numpy(estimated).double() - torch.stack(flows[:frames]).double())
        return errors

    def calibrate(self, state: OptimizerState, result: Evaluation, frames: int) -> OptimizerState:
        """Keep the flow estimator's error on the simulation ``result`` (at state.z, its first
        ``frames`` frames) as each view's ``estimator_error`` (saved in
        ``output/estimator_error.npz``). The loss then compares the simulated flow with the
        observed flow less that error, so the estimator's systematic error (DIS blends a
        moving object with its background, docs/flow.md) cancels instead of biasing the
        parameters."""
        calibrated_at = {"z": dict(state.z), "frames": frames, "grid": result.grid}
        if state.calibrated_at == calibrated_at:  # back at the point measured last (a rejected step)
            return state
        errors = []
        for view, error in zip(self.views, self.estimator_errors(result, frames)):
            full = torch.zeros_like(view.observed) if view.estimator_error is None else view.estimator_error.clone()
            full[:frames] = error
            errors.append(full.numpy())
        self.set_estimator_errors(errors)
        self.save_calibration(calibrated_at)
        return dataclasses.replace(state, calibrated_at=calibrated_at)

    def set_estimator_errors(self, errors: list[np.ndarray] | None) -> None:
        """Each view's estimator error [T, H, W, 2] (None: none), the cached evaluations rescored."""
        for i, view in enumerate(self.views):
            view.estimator_error = None if errors is None else torch.from_numpy(np.array(errors[i]))
        self._lm_cache = {key: (self.rescored(cached), J) for key, (cached, J) in self._lm_cache.items()}

    def restore_estimator_errors(self, calibrated_at: dict | None, errors: list | None) -> None:
        """Each view's estimator error back to ``errors`` (as measured at ``calibrated_at``),
        saved again as the calibration file's content."""
        self.set_estimator_errors(None if errors is None or errors[0] is None else errors)
        if calibrated_at is not None:
            self.save_calibration(calibrated_at)

    def save_calibration(self, calibrated_at: dict) -> None:
        """The views' estimator errors, measured at ``calibrated_at``, into ``estimator_error_file``."""
        with atomic_path(self.estimator_error_file) as tmp, open(tmp, "wb") as fh:
            np.savez(
                fh,
                key=np.array(json.dumps(calibrated_at, sort_keys=True)),
                **{f"view_{i}": view.estimator_error.numpy() for i, view in enumerate(self.views)},
            )

    def restore_calibration(self, state: OptimizerState) -> None:
        """Each view's estimator error as it was when ``state`` was saved (on --resume): from
        output/estimator_error.npz, or measured again at ``state.calibrated_at``."""
        key = json.dumps(state.calibrated_at, sort_keys=True)
        try:
            with np.load(self.estimator_error_file) as data:
                if str(data["key"]) == key:
                    self.set_estimator_errors([data[f"view_{i}"] for i in range(len(self.views))])
                    return
        except (OSError, KeyError, ValueError):
            pass
        log.info("measuring the flow estimator's error again at the checkpoint's calibration point")
        z, frames = state.calibrated_at["z"], state.calibrated_at["frames"]
        grid = state.calibrated_at.get("grid", self.model_grid)
        at = dataclasses.replace(state, z=dict(z), calibrated_at=None)  # measured there, whatever state.z is now
        self.calibrate(at, self.evaluate(z, frames, with_grad=False, min_substeps=state.substeps, grid=grid), frames)

    @property
    def corrects_bias(self) -> bool:
        return self.cfg.flow.bias_correction == "simulated"

    def loss_of(self, view_flows: list[list[torch.Tensor]], errors: list[torch.Tensor] | None = None) -> torch.Tensor:
        """The flow loss of each view's simulated flows (T of [H, W, 2]) against its target (or
        against its observed flow less ``errors``, the estimator's error per view), the mean
        over views."""
        if errors is None:
            targets = [view.target for view in self.views]
        else:
            targets = [view.observed[: len(error)] - error for view, error in zip(self.views, errors)]
        return sum(
            flow_loss(self.cfg, flows, target[: len(flows)], view.weight[: len(flows)])
            for flows, target, view in zip(view_flows, targets, self.views)
        ) / len(self.views)

    def self_consistent_loss(self, result: Evaluation, frames: int) -> float:
        """``result``'s loss against the observed flow less the estimator's error on ``result``'s
        own simulation: the video's estimated flow against the simulation's, estimated alike
        (with flow.bias_correction; else its loss)."""
        if not self.corrects_bias:
            return result.loss
        return float(self.loss_of([result.flows, *result.more_flows], self.estimator_errors(result, frames)))

    def rescored(self, result: Evaluation) -> Evaluation:
        """``result`` with its loss against the current targets (after a calibration)."""
        return dataclasses.replace(result, loss=float(self.loss_of([result.flows, *result.more_flows])))

    # -- the global phase ------------------------------------------------------------------

    def search_box(self, z0: dict[str, float]) -> dict[str, tuple[float, float]]:
        """(lower, upper) in z of each parameter's search box: ``optimize.bounds`` when
        given; else a log parameter's start times 10^(+-decades) within its typical range,
        and a bounded or linear one's typical range; each widened to hold the start."""
        opt = self.cfg.optimize
        box = {}
        for name, p in self.params.items():
            if name in opt.bounds:
                lo, hi = (float(p.encode(v)) for v in opt.bounds[name])
                if not lo <= z0[name] <= hi:
                    raise InputError(
                        f"{self.cfg.source}: the start of {name} lies outside optimize.bounds.{name} "
                        f"{list(opt.bounds[name])}"
                    )
            else:
                lo, hi = self.typical_box(name)
                if p.param.scale == "log":
                    lo, hi = max(lo, z0[name] - opt.search.decades), min(hi, z0[name] + opt.search.decades)
                lo, hi = min(lo, z0[name]), max(hi, z0[name])
            box[name] = (lo, hi)
        return box

    def search_points(self, z0: dict[str, float]) -> list[dict[str, float]]:
        """The global phase's design: the start, then a scrambled Sobol sequence (seed 0,
        reproducible) over the search box."""
        box = self.search_box(z0)
        names = list(self.params)
        count = self.cfg.optimize.search.samples
        unit = torch.quasirandom.SobolEngine(len(names), scramble=True, seed=0).draw(
            max(0, count - 1), dtype=torch.float64
        )
        points = [dict(z0)]
        for row in unit.tolist():
            points.append({**z0, **{n: box[n][0] + u * (box[n][1] - box[n][0]) for n, u in zip(names, row)}})
        return points

    def neighbourhoods(
        self, rows: list[dict], z0: dict[str, float]
    ) -> list[tuple[int, dict[str, tuple[float, float]]]]:
        """The second round's regions: (index into ``rows``, box in z) around each of the best
        ``search.starts`` first-round samples (``rows``) that lie outside each other's box,
        best first. A box spans one first-round spacing per parameter (the search box's width
        / samples^(1/parameters)) centred on its sample, cut to the search box."""
        box, names = self.search_box(z0), list(self.params)
        spacing = {n: (box[n][1] - box[n][0]) * len(rows) ** (-1.0 / len(names)) for n in names}
        ranked = sorted((i for i, r in enumerate(rows) if r["loss"] is not None), key=lambda i: rows[i]["loss"])
        centres: list[int] = []
        for i in ranked:
            if len(centres) == self.cfg.optimize.search.starts:
                break
            z = rows[i]["z"]
            if all(max(abs(z[n] - rows[c]["z"][n]) / spacing[n] for n in names) > 0.5 for c in centres):
                centres.append(i)
        return [
            (
                i,
                {
                    n: (
                        max(box[n][0], rows[i]["z"][n] - spacing[n] / 2),
                        min(box[n][1], rows[i]["z"][n] + spacing[n] / 2),
                    )
                    for n in names
                },
            )
            for i in centres
        ]

    def refinement_points(
        self, regions: list[tuple[int, dict[str, tuple[float, float]]]], z0: dict[str, float]
    ) -> list[tuple[int, dict[str, float]]]:
        """The second round's design: (centre's index, z) for ``search.refine`` samples shared
        among the :meth:`neighbourhoods` ``regions`` (the first refine % regions one more),
        a scrambled Sobol sequence (seed 1) in each."""
        if not regions:
            return []
        names, total = list(self.params), self.cfg.optimize.search.refine
        counts = [total // len(regions) + (k < total % len(regions)) for k in range(len(regions))]
        unit = torch.quasirandom.SobolEngine(len(names), scramble=True, seed=1).draw(max(counts), dtype=torch.float64)
        return [
            (i, {**z0, **{n: region[n][0] + u * (region[n][1] - region[n][0]) for n, u in zip(names, row)}})
            for (i, region), count in zip(regions, counts)
            for row in unit[:count].tolist()
        ]

    def global_search(self, state: OptimizerState) -> OptimizerState:
        """Forward-only losses at the search design, then (``search.refine``) at a second
        round around the best distinct samples (resuming after the samples already in
        ``state.search``); returns the state with z at the best sample, ``searched`` and the
        starts: the best sample of each neighbourhood with a second round, else the best
        ``search.starts`` samples. With ``flow.bias_correction``, each sample's loss is
        against the observed flow less the estimator's error on that sample's own simulation
        (the video's estimated flow against the simulation's, estimated alike)."""
        settings = self.cfg.optimize.search
        frames = min(self.frames, settings.frames or self.frames)
        rows = list(state.search)

        def sample(z: dict[str, float], around: int | None = None) -> None:
            nonlocal state
            start = time.perf_counter()
            try:
                loss = self.self_consistent_loss(
                    self.evaluate(z, frames, with_grad=False, grid=self.search_grid), frames
                )
            except (FloatingPointError, ClflowError) as exc:
                log.info("search sample %s failed: %s", self.values(z), exc)
                loss = None
            neighbourhood = {} if around is None else {"around": around}
            rows.append(
                {"z": z, "params": self.values(z), "loss": loss, "frames": frames, **neighbourhood}
                | {"grid": self.search_grid, "seconds": time.perf_counter() - start}
            )
            state = dataclasses.replace(state, search=list(rows))
            self.save_state(state)
            self.progress({**rows[-1], "phase": "search", "iteration": len(rows) - 1})

        design = self.search_points(state.z)
        for z in design[len(rows) :]:
            sample(z)
        first = rows[: len(design)]
        if not any(r["loss"] is not None for r in first):
            raise ClflowError(f"the global search found no parameters whose simulation ran ({len(rows)} samples)")
        regions = self.neighbourhoods(first, state.z) if settings.refine else []
        second = self.refinement_points(regions, state.z)
        for around, z in second[len(rows) - len(design) :]:
            sample(z, around)
        finite = [r for r in rows if r["loss"] is not None]
        ranked = sorted(finite, key=lambda r: r["loss"])
        best = ranked[0]
        log.info("global search: best of %d samples %s (loss %.4g)", len(rows), best["params"], best["loss"])
        if regions:  # each neighbourhood's best, its centre included
            groups = [[rows[i]] + [r for r in rows[len(design) :] if r.get("around") == i] for i, _ in regions]
            picks = sorted(
                (min(g, key=lambda r: r["loss"] if r["loss"] is not None else math.inf) for g in groups),
                key=lambda r: r["loss"],
            )
        else:
            picks = ranked[: settings.starts]
        starts = [dict(r["z"]) for r in picks] if settings.starts > 1 else []
        state = dataclasses.replace(state, z=dict(best["z"]), searched=True, starts=starts)
        self.save_state(state)
        return state

    def polish(self, begin: OptimizerState, start: int, resume: bool = False, budget: int | None = None) -> dict:
        """Levenberg-Marquardt from search start ``start`` (``begin``: the state the search
        ended in) for ``search.start_iterations`` iterations or until it converges, as if no
        other start ran: its own time step (substeps from 1; the first start keeps begin's),
        calibration, rollbacks and horizon schedule. Checkpointed in ``output/starts/<start>/``
        (``resume`` goes on from there; ``budget``: at most this many iterations now).
        Returns {"state": its end state (asdict), "errors": each view's estimator error
        [T, H, W, 2] at its end (None without flow.bias_correction), "finished",
        "iterations_here"}."""
        folder = self.cfg.output / "starts" / str(start)
        z0 = dict(begin.starts[start])
        main_file, self.estimator_error_file = self.estimator_error_file, folder / "estimator_error.npz"
        try:
            self._lm_cache = {}
            self.set_estimator_errors(None)  # nothing measured yet (a saved polish restores its own)
            state = self.load_polish(folder / "checkpoint.json", z0) if resume else None
            if state is None:
                state = dataclasses.replace(
                    begin,
                    z=z0,
                    substeps=begin.substeps if start == 0 else 1,
                    best=None,
                    damping=LM_DAMPING,
                    converged=False,
                    calibrated_at=None,
                    history=list(begin.history),
                    rollbacks=list(begin.rollbacks),
                )
            failures, done = 0, 0
            last = state.history[-1] if state.history else {}
            finished = last.get("start") == start and bool(last.get("start_done"))
            while not finished and (budget is None or done < budget):
                state, failures, row = self.step(state, failures, start)
                if row is None:
                    continue
                finished, done = bool(row.get("start_done")), done + 1
                self.save_state(state, folder / "checkpoint.json", start=z0)
                self.progress(row)
            errors = None if state.calibrated_at is None else [v.estimator_error.numpy() for v in self.views]
        finally:
            self.estimator_error_file = main_file
        return {"state": asdict(state), "errors": errors, "finished": finished, "iterations_here": done}

    def load_polish(self, checkpoint: Path, z0: dict[str, float]) -> OptimizerState | None:
        """A start's polish as saved in ``checkpoint`` (its calibration restored), None when
        there is none of this config and start point."""
        try:
            data = json.loads(checkpoint.read_text())
            state = OptimizerState(**data["state"])
        except (OSError, ValueError, KeyError, TypeError):
            return None
        ours = (config_digests(self.cfg), config_digests(self.cfg, by_path=True))
        if data.get("start") != z0 or data.get("config_digests") not in ours:
            return None
        if state.calibrated_at is not None:
            self.restore_calibration(state)
        return state

    def keep_best_start(self, begin: OptimizerState, records: list[dict]) -> OptimizerState:
        """The state after every start's polish (``records`` of :meth:`polish`, in start
        order, from ``begin``): their rows and rollbacks one after another, iterations
        numbered on; each start's best point in ``polished``; z at the best of them, with its
        substeps and calibration, and Levenberg-Marquardt's memory reset. With a coarser
        search grid the best is the one whose loss is least on the main phase's grid (each
        against the estimator's error at its own point), where the result comes from."""
        history, rollbacks, polished, ends = list(begin.history), list(begin.rollbacks), [], []
        iteration = begin.iteration
        for record in records:
            end = OptimizerState(**record["state"])
            shift = iteration - begin.iteration
            history += [{**r, "iteration": r["iteration"] + shift} for r in end.history[len(begin.history) :]]
            rollbacks += [{**r, "iteration": r["iteration"] + shift} for r in end.rollbacks[len(begin.rollbacks) :]]
            iteration += end.iteration - begin.iteration
            polished.append(
                {
                    "z": dict(end.best["z"]),
                    "loss": end.best["loss"],
                    "params": self.values(end.best["z"]),
                    "substeps": end.substeps,
                }
            )
            ends.append(end)
        ranking = "loss"
        if self.search_grid != self.model_grid and len(polished) > 1:
            ranking = "model_loss"
            for record in polished:
                try:
                    result = self.evaluate(record["z"], self.frames, with_grad=False, min_substeps=record["substeps"])
                    record["model_loss"] = self.self_consistent_loss(result, self.frames)
                except (FloatingPointError, ClflowError) as exc:
                    log.info("start %s fails on the main phase's grid: %s", record["params"], exc)
                    record["model_loss"] = math.inf
        index = min(range(len(polished)), key=lambda i: polished[i][ranking])
        kept = polished[index]
        log.info(
            "kept start %d of %d: %s (%s %.4g; the others %s)",
            index,
            len(polished),
            kept["params"],
            "loss on the main phase's grid" if ranking == "model_loss" else "loss",
            kept[ranking],
            ", ".join(f"{r[ranking]:.4g}" for r in polished if r is not kept),
        )
        state = dataclasses.replace(
            begin,
            iteration=iteration,
            history=history,
            rollbacks=rollbacks,
            polished=polished,
            z=dict(kept["z"]),
            substeps=kept["substeps"],
            best=None,
            damping=LM_DAMPING,
            converged=False,
            calibrated_at=ends[index].calibrated_at,
        )
        self.restore_estimator_errors(state.calibrated_at, records[index]["errors"])
        return state

    # -- Levenberg-Marquardt ----------------------------------------------------------------

    def residuals(self, flows: list[torch.Tensor], more_flows: tuple[list[torch.Tensor], ...] = ()) -> torch.Tensor:
        """[R] float64 flow residuals whose sum of squares is the l2 flow loss of ``flows``
        (simulated [H, W, 2] per frame step; ``more_flows`` those of views 1..), weighted by
        mask x confidence like the loss."""
        parts = []
        for view_flows, view in zip([flows, *more_flows], self.views):
            weight = view.weight[: len(view_flows)]  # [T, H, W]
            root = (weight / weight.sum() / len(self.views)).sqrt()[..., None]
            target = view.target
            parts += [((f.double() - target[t]) * root[t])[weight[t] > 0].reshape(-1) for t, f in enumerate(view_flows)]
        return torch.cat(parts)

    def jacobian(
        self, z: dict[str, float], frames: int, min_substeps: int, variables: tuple[str, ...], grid: int
    ) -> tuple[Evaluation, torch.Tensor]:
        """The evaluation at z on the grid of ``grid`` nodes and the Jacobian [R, P] of its
        residuals with respect to ``variables`` by backward differences of LM_STEP (softer
        neighbours need no more substeps than z, so every run shares z's time step); the last
        two are cached."""
        key = (tuple(sorted(z.items())), frames, variables, grid, min_substeps)
        if key in self._lm_cache:
            self._lm_cache[key] = self._lm_cache.pop(key)  # the most recent: kept by the next miss
            return self._lm_cache[key]
        base = self.evaluate(z, frames, with_grad=False, min_substeps=min_substeps, grid=grid)
        r0 = self.residuals(base.flows, base.more_flows)
        columns = []
        for name in variables:
            nearby = self.evaluate(
                {**z, name: z[name] - LM_STEP}, frames, with_grad=False, min_substeps=base.substeps, grid=grid
            )
            columns.append((r0 - self.residuals(nearby.flows, nearby.more_flows)) / LM_STEP)
        J = torch.stack(columns, 1)
        # kept under the substeps the run used: a revisit asks for those (a retried run restarts
        # from frame 0 at the raised count, so it equals a run asked for that count)
        used = (*key[:4], base.substeps)
        self._lm_cache = {**dict(list(self._lm_cache.items())[-1:]), used: (base, J)}
        return base, J

    def lm_step(
        self,
        state: OptimizerState,
        base: Evaluation,
        J: torch.Tensor,
        frames: int,
        variables: tuple[str, ...],
        calibrate: bool = False,
    ) -> OptimizerState:
        """Accept or reject the point just evaluated (its loss against the best so far at this
        horizon), then one damped Gauss-Newton step from the best point:
        (J^T J + damping diag(J^T J)) dz = -J^T r, held at most LM_MAX_STEP x step_scale long
        by :meth:`trust_region_step` (a rejection quarters the radius, an accepted point
        doubles it up to 1; Marquardt's damping alone hardly shortens a step along a direction
        the loss barely sees). With ``calibrate``, an accepted point first measures the flow
        estimator's error (the residuals' Jacobian does not depend on it)."""
        best = state.best
        moved = best is not None and state.z != best["z"]
        # only a new point is judged against the best one: back at the best point (after a
        # rejection) its loss is taken as it comes out, never rejected against itself (a
        # checkpoint from before best recorded its substeps may re-run it at another step)
        comparable = moved and best["frames"] == frames

        def reject(**more) -> OptimizerState:
            # back to the best point with more damping and a radius of a quarter of the step
            # just rejected (More's rule): a quarter of the radius alone, when the step lay far
            # inside it, returns the same step (the trophy tried one 0.06 degree step 3 times)
            taken = math.sqrt(sum((state.z[n] - best["z"][n]) ** 2 for n in variables))
            return dataclasses.replace(
                state,
                iteration=state.iteration + 1,
                z=dict(best["z"]),
                damping=state.damping * 4.0,
                step_scale=min(state.step_scale, taken / LM_MAX_STEP) / 4.0,
                **more,
            )

        if comparable and base.loss > best["loss"]:  # uphill (the best point's J is cached)
            return reject()
        # a new best point earns less damping and a longer step; back at the best one after a
        # rejection, the raised damping and shorter step stand (else it retries the same step)
        damping = state.damping / 3.0 if moved else state.damping
        step_scale = min(1.0, 2.0 * state.step_scale) if moved else state.step_scale
        if calibrate:
            before = state.calibrated_at, [view.estimator_error for view in self.views]
            state = self.calibrate(state, base, frames)
            base = self.rescored(base)
            if comparable and base.loss > best["loss"]:
                # downhill only against the best point's calibration; against its own (each
                # point's loss against the estimator's error on its own simulation, as the
                # search scores) it is worse: the step chased the estimator's error, reject it
                log.info(
                    "step to %s rejected: loss %.4g against the estimator's error there, %.4g at the best point",
                    self.values(state.z),
                    base.loss,
                    best["loss"],
                )
                self.restore_estimator_errors(*before)
                return reject(calibrated_at=before[0])
        best = {"z": dict(state.z), "loss": base.loss, "frames": frames, "substeps": base.substeps}
        r = self.residuals(base.flows, base.more_flows)
        A, g = J.T @ J, J.T @ r
        diagonal = torch.diag(torch.diag(A).clamp(min=1e-12 * float(torch.diag(A).max().clamp(min=1e-30))))
        M = A + damping * diagonal
        # the model's fall of the residuals' sum of squares along its own step: after a few
        # rejections the trust region's step is short and promises little wherever it points
        full = self.bounded_step(M, g, state.z, variables)
        if -float(2 * g @ full + full @ A @ full) <= LM_GAIN_TOLERANCE * float(r @ r):
            return dataclasses.replace(
                state, iteration=state.iteration + 1, damping=damping, step_scale=step_scale, best=best, converged=True
            )
        step = self.trust_region_step(M, g, state.z, variables, LM_MAX_STEP * step_scale)
        z = {**state.z, **{n: state.z[n] + float(d) for n, d in zip(variables, step)}}
        return dataclasses.replace(
            state, iteration=state.iteration + 1, z=z, damping=damping, step_scale=step_scale, best=best
        )

    @functools.cached_property
    def _local_box(self) -> dict[str, tuple[float, float]]:
        return self.search_box(self.initial_state().z) if self.cfg.optimize.search is not None else {}

    def local_box(self) -> dict[str, tuple[float, float]]:
        """(lower, upper) in z that the local phase stays in: the search's box (none without a search)."""
        return self._local_box

    def bounded_step(
        self, M: torch.Tensor, g: torch.Tensor, z: dict[str, float], variables: tuple[str, ...]
    ) -> torch.Tensor:
        """The step [P] solving M step = -g, with a variable that sits on its box edge while the
        step would push it out held there and the rest solved again without it (the clipped
        step would otherwise promise what it cannot deliver, and rejected steps repeat)."""
        box = self.local_box()
        free = torch.ones(len(variables), dtype=torch.bool)
        step = torch.zeros_like(g)
        while bool(free.any()):
            index = free.nonzero().flatten()
            step = torch.zeros_like(g)
            step[index] = -torch.linalg.solve(M[index][:, index], g[index])
            held = torch.tensor(
                [
                    bool(free[i])
                    and n in box
                    and (z[n] <= box[n][0] and float(step[i]) < 0 or z[n] >= box[n][1] and float(step[i]) > 0)
                    for i, n in enumerate(variables)
                ]
            )
            if not bool(held.any()):
                break
            free &= ~held
            step = torch.zeros_like(g)
        return step

    def trust_region_step(
        self, M: torch.Tensor, g: torch.Tensor, z: dict[str, float], variables: tuple[str, ...], radius: float
    ) -> torch.Tensor:
        """The step of :meth:`bounded_step` for M + lam I, with the least lam >= 0 that keeps it
        at most ``radius`` long (z units; the trust-region Levenberg-Marquardt of More 1978).
        lam shortens a step most along the directions the loss sees least: scaling the whole
        step down instead shrinks a well-determined component (the cream's yield stress) as
        much as the poorly determined one (its viscosity) that made the step long. With a
        variable held on its box's edge for some lam and not others the length need not fall
        monotonically in lam: the step is then inside the radius but may be shorter."""
        step = self.bounded_step(M, g, z, variables)
        if float(step.norm()) <= radius:
            return step
        eye = torch.eye(len(variables), dtype=M.dtype)
        hi = float(torch.diag(M).max()) or 1.0
        lo = hi * 1e-12
        for _ in range(60):  # the step shrinks as g / lam for a large lam
            if float(self.bounded_step(M + hi * eye, g, z, variables).norm()) <= radius:
                break
            lo, hi = hi, hi * 10.0
        for _ in range(50):  # bisection in log lam: the step's length falls as lam grows
            mid = math.sqrt(lo * hi)
            if float(self.bounded_step(M + mid * eye, g, z, variables).norm()) > radius:
                lo = mid
            else:
                hi = mid
        return self.bounded_step(M + hi * eye, g, z, variables)

    # -- the gradient phase -----------------------------------------------------------------

    def adam_step(self, state: OptimizerState, grads: dict[str, float]) -> OptimizerState:
        """One Adam step in z, gradient clipped to CLIP_NORM, with adaptive restart
        (O'Donoghue and Candes 2015): when the last step went uphill along the new gradient
        (g . dz > 0), the momentum is dropped, so an overshoot turns back at once instead
        of coasting on for several iterations."""
        scale = clip_factor(math.sqrt(sum(g * g for g in grads.values())), CLIP_NORM)
        z, m, v = dict(state.z), dict(state.m), dict(state.v)
        k_m = state.momentum_steps + 1
        if state.history:
            last = state.history[-1]["z"]
            if sum(grads[n] * (z[n] - last[n]) for n in grads) > 0:
                m, k_m = {n: 0.0 for n in m}, 1
        _, iteration, iterations = phase_of(self.cfg.optimize, state.iteration)
        k = iteration + 1  # gradients in v since the phase began (for Adam's bias correction)
        schedule = rate_schedule(self.cfg.optimize, iteration, iterations)
        for n, g in grads.items():
            g *= scale
            m[n] = BETAS[0] * m[n] + (1 - BETAS[0]) * g
            v[n] = BETAS[1] * v[n] + (1 - BETAS[1]) * g * g
            m_hat, v_hat = m[n] / (1 - BETAS[0] ** k_m), v[n] / (1 - BETAS[1] ** k)
            rate = learning_rate(self.cfg, n) * state.step_scale * schedule
            z[n] -= rate * m_hat / (math.sqrt(v_hat) + ADAM_EPS)
        return dataclasses.replace(
            state, iteration=state.iteration + 1, z=z, m=m, v=v, history=list(state.history), momentum_steps=k_m
        )

    def run(
        self, resume: bool = False, stop_after: int | None = None, start: OptimizerState | None = None
    ) -> OptimizerState:
        """Optimise for the velocity phase's and ``optimize.iterations`` iterations
        (``stop_after``: at most this many in this call, for tests of resuming), from the
        checkpoint (``resume``), else ``start``, else the initial state; returns the final
        state. Each phase starts with fresh Adam moments and step scale. The starts'
        polishes (``optimize.search.starts``) run through ``self.map_starts``."""
        opt = self.cfg.optimize
        self.cfg.output.mkdir(parents=True, exist_ok=True)
        if resume and self.checkpoint.exists():
            state = self.load_state()
        else:
            state = start or self.initial_state()
        failures, done_here = 0, 0
        while state.iteration < self.total_iterations and (stop_after is None or done_here < stop_after):
            if phase_of(opt, state.iteration)[0] == "main" and opt.search is not None and not state.searched:
                state = self.global_search(state)  # after the velocity phase: from its estimate
            if len(state.polished) < len(state.starts):
                budget = None if stop_after is None else stop_after - done_here
                polish_all = self.map_starts if budget is None else serial_starts  # stop_after: tests, here
                records = polish_all(self, state, range(len(state.starts)), resume, budget)
                done_here += sum(r["iterations_here"] for r in records)
                if not all(r["finished"] for r in records):  # stopped by stop_after
                    return state
                state = self.keep_best_start(state, records)
                self.save_state(state)
                continue
            state, failures, row = self.step(state, failures)
            if row is not None:
                self.save_state(state)
                self.progress(row)
                done_here += 1
        best = state.best
        if (
            opt.method == "levenberg_marquardt"
            and best is not None
            and state.iteration >= self.total_iterations
            and state.z != best["z"]
        ):  # the last step was never run: the result is the best point found
            state = dataclasses.replace(state, z=dict(best["z"]), substeps=best.get("substeps", state.substeps))
            self.save_state(state)
        return state

    def step(
        self, state: OptimizerState, failures: int, start: int | None = None
    ) -> tuple[OptimizerState, int, dict | None]:
        """One iteration from ``state`` (``start``: of that start's polish), ``failures`` the
        consecutive failed ones before it. Returns the new state, the failures, and the
        iteration's history row (None when it failed and was rolled back)."""
        opt = self.cfg.optimize
        lm = opt.method == "levenberg_marquardt"
        phase, iteration, _ = phase_of(opt, state.iteration)
        if phase == "velocity":
            frames, variables = opt.estimate_velocity_frames, VELOCITY_COMPONENTS
        else:
            frames, variables = horizon(self.cfg, iteration), self.main_variables
        grid = self.model_grid if start is None else self.search_grid  # a start's polish: the global phase's
        began = time.perf_counter()
        try:
            if lm:
                result, J = self.jacobian(state.z, frames, state.substeps, variables, grid)
            else:
                result = self.evaluate(state.z, frames, min_substeps=state.substeps, variables=variables, grid=grid)
        except (FloatingPointError, ClflowError) as exc:
            failures += 1
            # a start's polish goes back within its own rows only (else to its start point)
            own = [r for r in state.history if start is None or r.get("start") == start]
            if failures > MAX_FAILURES or state.iteration == 0 and start is None and failures > 1:
                good = (
                    f"last good parameters: {self.values(own[-1]['z'])}"
                    if own
                    else f"the initial parameters {self.values(state.z)} fail"
                )
                raise ClflowError(
                    f"optimisation stopped at iteration {state.iteration}: {exc} ({failures} failed attempts); {good}"
                )
            previous = own[-1]["z"] if own else state.z
            log.warning(
                "iteration %d failed (%s): back to the last good parameters, half the step, momentum dropped",
                state.iteration,
                exc,
            )
            rollback = {
                "iteration": state.iteration,
                "phase": phase,
                "reason": str(exc),
                "params": self.values(state.z),
                "back_to": self.values(previous),
            }
            state = dataclasses.replace(
                state,
                z=dict(previous),
                m={n: 0.0 for n in state.m},
                step_scale=state.step_scale / 2,
                momentum_steps=0,
                damping=state.damping * 4.0,
                rollbacks=[*state.rollbacks, rollback],
            )
            return state, failures, None
        row = {
            "iteration": state.iteration,
            "phase": phase,
            "loss": result.loss,
            "frames": frames,
            "z": dict(state.z),
            "params": self.values(state.z),
            "substeps": result.substeps,
            "grid": grid,
            "seconds": time.perf_counter() - began,
        }
        previous = state
        calibrate = self.corrects_bias and phase == "main"
        if lm:
            state = self.lm_step(state, result, J, frames, variables, calibrate=calibrate)
        else:
            if calibrate:  # the next iteration fits the error measured here
                state = self.calibrate(state, result, frames)
            state = self.adam_step(state, result.grads)
        if state.calibrated_at is not previous.calibrated_at:
            row["calibrated"] = True
        if phase == "main":  # the local phase stays in the search's box
            box = self.local_box()
            state.z = {n: min(max(v, box[n][0]), box[n][1]) if n in box else v for n, v in state.z.items()}
        if lm and state.best is not None:
            # back at the best point (after a rejection) the run takes its time step, as the
            # cached Jacobian did; a step from it runs at its own stable step, as the search and
            # the truth's loss do: neither a rejected trial that needed more substeps nor a stiff
            # start leaves a finer, slower (and with APIC more damped, docs/mpm.md) model behind
            # for every later point
            state.substeps = state.best.get("substeps", result.substeps) if state.z == state.best["z"] else 1
        else:
            state.substeps = max(state.substeps, result.substeps)
        converged = (
            lm
            and phase == "main"
            and (
                state.converged
                or (
                    state.best is not None
                    and state.best is not previous.best
                    and max(abs(state.z[n] - state.best["z"][n]) for n in variables) < LM_TOLERANCE
                )
            )
        )
        if start is not None:  # a start's polish ends after its iterations or when it converges
            row["start"] = start
            done = 1 + sum(1 for r in state.history if r.get("start") == start)
            if converged or done >= opt.search.start_iterations:
                row["start_done"] = True
        elif converged:
            row["converged"] = True  # the step would change nothing that matters: stop here
            state = dataclasses.replace(state, iteration=self.total_iterations)
        elif lm and phase == "velocity" and state.converged:  # on to the main phase
            row["converged"] = True
            state = dataclasses.replace(state, iteration=opt.estimate_velocity_iterations)
        state.history.append(row)
        if phase_of(opt, state.iteration)[0] != phase:
            state = dataclasses.replace(
                state,
                m={n: 0.0 for n in state.m},
                v={n: 0.0 for n in state.v},
                momentum_steps=0,
                step_scale=1.0,
                damping=LM_DAMPING,
                best=None,
                converged=False,
            )
        return state, 0, row

    # -- results -------------------------------------------------------------------------

    def identifiability(self, z: dict[str, float], min_substeps: int) -> dict:
        """How well the video pins down each variable at z: from the residuals' Jacobian J
        (one forward run per variable), the Gauss-Newton covariance s^2 (J^T J)^-1 with s^2
        the loss per residual degree of freedom. Its standard errors (z units: decades for
        log-scale parameters) treat pixels as independent, so they are lower bounds; the
        correlations show which parameters trade off. ``loss_rise``: the fraction of the loss
        that a step of WEAK_STD_Z costs with the others refitted; a variable is weakly
        constrained when its standard error exceeds WEAK_STD_Z or that rise is below
        MIN_LOSS_RISE. Each weakly constrained material parameter is then profiled
        (:meth:`profile`, two forward runs): ``unresolved`` lists those whose loss is
        :func:`flat` over the range. ``grid_shift_z``: how far each variable's best fit moves
        on a coarser grid (:meth:`grid_shift`); ``grid_sensitive`` those moved beyond
        WEAK_STD_Z, whose value the discretisation sets as much as the video."""
        variables = self.main_variables
        base, J = self.jacobian(z, self.frames, min_substeps, variables, self.model_grid)
        residuals, count = self.residuals(base.flows, base.more_flows), len(variables)
        dof = max(1, residuals.numel() - count)
        curvature = J.T @ J
        ridge = 1e-12 * float(curvature.diagonal().max().clamp(min=1e-300))  # an unconstrained direction: huge
        inverse = torch.linalg.inv(curvature + ridge * torch.eye(count, dtype=curvature.dtype))
        loss = float((residuals**2).sum())
        covariance = inverse * (loss / dof)
        std = covariance.diagonal().clamp(min=0).sqrt()
        correlation = covariance / torch.outer(std, std).clamp(min=1e-300)
        # the loss a step of WEAK_STD_Z costs, the other variables refitted, as a fraction of the loss
        rise = (WEAK_STD_Z**2 / inverse.diagonal().clamp(min=1e-300) / max(loss, 1e-300)).tolist()
        weak = [n for n, sd, r in zip(variables, std.tolist(), rise) if not (sd <= WEAK_STD_Z and r >= MIN_LOSS_RISE)]
        pairs = [
            [a, b, float(correlation[i, j])]
            for i, a in enumerate(variables)
            for j, b in enumerate(variables)
            if i < j and abs(float(correlation[i, j])) > TRADE_OFF_CORRELATION
        ]
        profile = self.profile(z, base.substeps, weak, loss)
        coarse_grid, shift = self.grid_shift(z, base, J, inverse, variables)
        return {
            "std_z": dict(zip(variables, std.tolist())),
            "loss_rise": dict(zip(variables, rise)),
            "correlation": {a: dict(zip(variables, row)) for a, row in zip(variables, correlation.tolist())},
            "weakly_constrained": weak,
            "trade_offs": pairs,
            "profile": profile,
            "profile_rise": PROFILE_RISE,
            "unresolved": [n for n, row in profile.items() if flat(row)],
            "grids": [coarse_grid, self.model_grid],
            "grid_shift_z": shift,
            "grid_sensitive": [n for n, moved in shift.items() if abs(moved) > WEAK_STD_Z],
        }

    def grid_shift(
        self, z: dict[str, float], base: Evaluation, J: torch.Tensor, inverse: torch.Tensor, variables: tuple[str, ...]
    ) -> tuple[int, dict[str, float]]:
        """(the coarser grid's nodes, per variable the move of the best fit in z units from
        the model grid to that grid): the final point ``base`` (residual Jacobian ``J``
        [R, P], ``inverse`` = (J^T J)^-1) run again, forward only, on the search grid, or one
        GRID_CHECK_RATIO times coarser without a coarser search grid; to first order the fit
        moves by -(J^T J)^-1 J^T (r_coarse - r_model), both against the same targets. The
        discretisation's pull on each estimate at the scale of the grid refinement: the
        model grid's own bias is of that order too (its sign and size depend on how fast the
        estimate converges with the grid). Where the coarser grid's thicker walls leave the
        object no room in the domain, a GRID_CHECK_RATIO times finer grid instead. Empty
        where the run fails."""
        coarse = self.search_grid
        if coarse >= self.model_grid:
            coarse = round((self.model_grid - 1) / GRID_CHECK_RATIO) + 1
        finer = round((self.model_grid - 1) * GRID_CHECK_RATIO) + 1
        try:
            self.prepared_on(coarse)
        except InputError:
            log.info("the grid check takes %d nodes: on %d the thicker walls leave the object no room", finer, coarse)
            coarse = finer
        try:
            run = self.evaluate(z, self.frames, with_grad=False, grid=coarse)
        except (FloatingPointError, ClflowError) as exc:
            log.info("the grid check at %d nodes failed: %s", coarse, exc)
            return coarse, {}
        change = self.residuals(run.flows, run.more_flows) - self.residuals(base.flows, base.more_flows)
        moved = -(inverse @ (J.T @ change))
        return coarse, dict(zip(variables, moved.tolist()))

    def profile(self, z: dict[str, float], min_substeps: int, names: list[str], loss: float) -> dict:
        """Per material parameter in ``names``: ``values`` (SI) PROFILE_STEP below z, at z and
        PROFILE_STEP above in z units, cut to the local phase's box (else the parameter's
        typical range, widened to hold z; a side on its edge is left out), and ``loss_ratio``,
        the loss there with the others held over ``loss``, the loss at z (None where the run
        failed)."""
        out = {}
        for name in (n for n in names if n in self.params):
            lo, hi = self.local_box().get(name) or self.typical_box(name)
            lo, hi = min(lo, z[name]), max(hi, z[name])
            row: dict[str, list] = {"values": [], "loss_ratio": []}
            for target in sorted({max(lo, z[name] - PROFILE_STEP), z[name], min(hi, z[name] + PROFILE_STEP)}):
                moved, ratio = {**z, name: target}, 1.0
                if target != z[name]:
                    try:
                        ev = self.evaluate(moved, self.frames, with_grad=False, min_substeps=min_substeps)
                        ratio = float((self.residuals(ev.flows, ev.more_flows) ** 2).sum()) / max(loss, 1e-300)
                    except (FloatingPointError, ClflowError) as exc:
                        log.info("profile of %s at %s failed: %s", name, self.values(moved)[name], exc)
                        ratio = None
                row["values"].append(self.values(moved)[name])
                row["loss_ratio"].append(ratio)
            out[name] = row
        return out

    def typical_box(self, name: str) -> tuple[float, float]:
        """(lower, upper) in z of material parameter ``name``'s typical range."""
        p = self.params[name]
        lo, hi = (float(p.encode(v)) for v in p.param.typical) if p.param.scale != "linear" else p.param.typical
        return lo, hi

    def endpoint_error(self, flows: list[torch.Tensor], more_flows: tuple[list[torch.Tensor], ...] = ()) -> float:
        """Mean flow endpoint error (px) of simulated flows [H, W, 2] per frame step against
        the observed flow, inside the loss mask (``more_flows``: views 1..; the mean over views)."""
        from clflow.flow.metrics import endpoint_error

        return float(
            np.mean(
                [
                    np.mean(
                        [
                            endpoint_error(f.numpy(), view.observed[t].numpy(), view.mask.numpy())
                            for t, f in enumerate(view_flows)
                        ]
                    )
                    for view_flows, view in zip([flows, *more_flows], self.views)
                ]
            )
        )

    def write_results(self, state: OptimizerState) -> dict:
        """params.json, metrics.json, history.json, loss.png and comparison.mp4 in output/."""
        from clflow.flow.visualize import comparison_panel
        from clflow.media import write_video

        out = self.cfg.output
        # the identifiability check below needs this evaluation as its Jacobian's base: run it once
        try:
            result, _ = self.jacobian(state.z, self.frames, state.substeps, self.main_variables, self.model_grid)
        except (FloatingPointError, ClflowError) as exc:
            if not state.history:
                raise
            # the last step's point is not a result: back to the last accepted one (state changes in place)
            good = state.history[-1]["z"]
            log.warning("the final parameters fail (%s): the results are those of the last good ones", exc)
            state.rollbacks.append(
                {
                    "iteration": state.iteration,
                    "phase": "final",
                    "reason": str(exc),
                    "params": self.values(state.z),
                    "back_to": self.values(good),
                }
            )
            state.z = dict(good)
            self.save_state(state)
            result, _ = self.jacobian(state.z, self.frames, state.substeps, self.main_variables, self.model_grid)
        if self.corrects_bias:  # the results' loss against the estimator's error at the final parameters
            state.calibrated_at = self.calibrate(state, result, self.frames).calibrated_at
            self.save_state(state)
            result = self.rescored(result)
        final = self.values(state.z)
        params, density = material_values(self.cfg, {n: final[n] for n in self.params})
        velocity = self.velocity(state.z)
        loss, flows = result.loss, result.flows
        metrics = {
            "flow_loss": loss,
            "epe_px": self.endpoint_error(flows, result.more_flows),
            "iterations": len(state.history),
            "seconds_per_iteration": float(np.mean([h["seconds"] for h in state.history])) if state.history else 0.0,
        }
        metrics["rollbacks"] = state.rollbacks  # every rejected iteration: its reason and parameters
        if self.guidance:
            metrics["guidance_checks"] = [check.record() for check in self.guidance]
        if self.guidance_warnings:  # forced past a failed guidance check (--force-video)
            metrics["warnings"] = list(self.guidance_warnings)
        metrics["identifiability"] = self.identifiability(state.z, state.substeps)
        if self.hypotheses:
            metrics["material_hypotheses"] = self.hypotheses
        for name in metrics["identifiability"]["weakly_constrained"]:
            log.warning(
                "%s is weakly constrained by the video: standard error %.2g in the optimiser's units (a "
                "lower bound); its value is uncertain",
                name,
                metrics["identifiability"]["std_z"][name],
            )
        for name in metrics["identifiability"]["unresolved"]:
            values = metrics["identifiability"]["profile"][name]["values"]
            log.warning(
                "%s is not resolved by the video from %.3g to %.3g (SI): moved alone there, the loss changes by "
                "less than %d %%",
                name,
                min(values),
                max(values),
                round(100 * PROFILE_RISE),
            )
        coarse_grid = metrics["identifiability"]["grids"][0]
        for name in metrics["identifiability"]["grid_sensitive"]:
            log.warning(
                "%s depends on the grid: on %d nodes instead of %d its best fit moves by %+.2g in the "
                "optimiser's units; its value carries a discretisation error of about that size",
                name,
                coarse_grid,
                self.model_grid,
                metrics["identifiability"]["grid_shift_z"][name],
            )
        for a, b, rho in metrics["identifiability"]["trade_offs"]:
            log.warning("%s and %s trade off (correlation %.3f): the video fixes a combination of them", a, b, rho)
        truth = self.cfg.ground_truth
        if truth:
            metrics["relative_error"] = {n: abs(final[n] - truth[n]) / abs(truth[n]) for n in self.params if n in truth}
            if VELOCITY_COMPONENTS[0] in final and VELOCITY_COMPONENTS[0] in truth:
                true_velocity = [truth[n] for n in VELOCITY_COMPONENTS]
                metrics["velocity_error_m_s"] = math.dist(velocity, true_velocity)  # |v - v_true|
                if any(true_velocity):
                    metrics["relative_error"][VELOCITY] = metrics["velocity_error_m_s"] / math.hypot(*true_velocity)
        record = {
            "material": self.cfg.material.type,
            "parameters": params,
            "density": density,
            "velocity": list(velocity),
            "optimized": final,
            "units": {n: parameter_unit(self.cfg, n) for n in final},
            # the substeps per frame the final evaluation needed (after any CFL retry): a
            # re-simulation of this result (clflow simulate --params-from) takes at least these
            "substeps": result.substeps,
            "fps": self.cfg.simulation.fps,
        }
        atomic_write_text(out / "params.json", json.dumps(record, indent=2))
        atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2))
        atomic_write_text(out / "history.json", json.dumps(state.history, indent=1))
        if state.search:
            atomic_write_text(out / "search.json", json.dumps(state.search, indent=1))
        write_history_plot(out / "loss.png", state.history, truth)
        # per view, side by side: guidance | guidance flow | simulated flow | error, plus the simulated frames
        traj = result.trajectory
        simulated = SimulationResult(self.prepared, params, density, traj.x.detach(), traj.F.detach())
        for k, (view, view_flows) in enumerate(zip(self.views, [flows, *result.more_flows])):
            sim_frames = render_frames(simulated, camera=view.camera)
            max_flow = max(float(view.observed.norm(dim=-1).max()), 1e-6)
            panels = [
                np.concatenate(
                    [
                        comparison_panel(
                            view.video_frames[t], view.observed[t].numpy(), view_flows[t].numpy(), max_flow
                        ),
                        sim_frames[t],
                    ],
                    1,
                )
                for t in range(self.frames)
            ]
            write_video(out / comparison_video(k), np.stack(panels), self.cfg.simulation.fps)
        return metrics


def comparison_video(view: int) -> str:
    """The results' comparison video of guidance view ``view`` (0: the config's camera)."""
    return "comparison.mp4" if view == 0 else f"comparison_view{view}.mp4"


def _quiet(row: dict) -> None:
    """No progress shown."""


def serial_starts(
    opt: Optimization, begin: OptimizerState, starts, resume: bool = False, budget: int | None = None
) -> list[dict]:
    """Polish each of ``starts`` (indices into begin.starts) one after another in this process
    (``budget``: at most this many iterations in all); records of Optimization.polish."""
    records = []
    for k in starts:
        records.append(opt.polish(begin, k, resume=resume, budget=budget))
        if budget is not None:
            budget -= records[-1]["iterations_here"]
    return records


def _polish_task(opt, begin, start: int, resume: bool) -> dict:
    return opt.polish(begin, start, resume=resume)


def starts_on_ray(**ray_options) -> Callable:
    """An Optimization.map_starts (``clflow optimize --parallel``): each search start's polish a
    Ray task (clflow.parallel.map_on_ray, ``ray_options`` its keywords), its rows shown as it finishes."""

    def map_starts(opt, begin, starts, resume: bool = False, budget: int | None = None) -> list[dict]:
        starts = list(starts)

        def finished(index: int, record: dict) -> None:
            for row in record["state"]["history"][len(begin.history) :]:
                opt.progress(row)

        from clflow.parallel import map_on_ray

        return map_on_ray(_polish_task, [(opt, begin, k, resume) for k in starts], done=finished, **ray_options)

    return map_starts


def learning_rate(cfg: SceneConfig, name: str) -> float:
    """Learning rate of the z variable ``name`` per iteration (before the schedule): the
    config's, else DEFAULT_VELOCITY_RATE (m/s) for a velocity component and DEFAULT_RATE."""
    rates = cfg.optimize.learning_rates
    if name in VELOCITY_COMPONENTS:
        return rates.get(VELOCITY, DEFAULT_VELOCITY_RATE)
    return rates.get(name, DEFAULT_RATE)


def parameter_unit(cfg: SceneConfig, name: str) -> str:
    """SI unit of an optimised variable (of a config with a concrete material)."""
    from clflow.materials import DENSITY, get_material

    if name in VELOCITY_COMPONENTS:
        return "m/s"
    return DENSITY.unit if name == "density" else get_material(cfg.material.type).param(name).unit


__all__ = [
    "Optimization",
    "OptimizerState",
    "horizon",
    "learning_rate",
    "parameter_unit",
    "phase_of",
    "rate_schedule",
    "write_history_plot",
]
