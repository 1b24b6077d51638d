"""``clflow optimize``: material parameters from a guidance video's optical flow.

Each iteration: simulate (differentiable MPM) -> render the simulated flow from the guidance
camera -> masked flow loss against the video's flow -> adjoint -> one Adam step on the
parameters' unconstrained variables z (log10 for moduli, bounded maps for ratios: see
clflow.mpm.parameterization) with a cosine-decaying rate. The loss may cover only the first
frames at first (``optimize.horizon``): a short horizon keeps the loss monotone far from the
optimum, where a long one has local minima (docs/pipeline.md). Adam is written out here in float64 so that its whole state
goes into ``checkpoint.json`` after every iteration; ``resume`` continues from it and gives
the same result as an uninterrupted run. A failed iteration (NaN, a simulation that blows
up) rolls back to the last good parameters, halves the step and tries again.

Results in ``output/``: params.json, metrics.json, history.json, loss.png, comparison.mp4,
observed_flow.npz (the video's flow and its confidence, computed once).
"""

from __future__ import annotations

import dataclasses
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
from clflow.pipeline.forward import Prepared, SimulationResult, material_values, prepare, render_frames
from clflow.pipeline.material import resolve_material
from clflow.pipeline.render import frame_gaussians, render_flow, render_object_alpha
from clflow.pipeline.simulation import build_simulator, run
from clflow.scene.config import SceneConfig

log = logging.getLogger(__name__)

BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
DEFAULT_RATE = 0.1  # per iteration, in z units (a decade per 10 steps for log parameters)
MAX_FAILURES = 4  # consecutive failed iterations before giving up
CLIP_NORM = 10.0  # gradient clipping in z space


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
    # substeps per frame at least (automatic substeps): never fewer than an earlier iteration
    # needed, so the loss stays one smooth function of the parameters instead of jumping
    # where a NaN/CFL retry would change dt
    substeps: int = 1


@dataclass
class Evaluation:
    """The loss at one point: value, dloss/dz per parameter, simulated flows [H, W, 2] per
    frame step, and the simulation (x [T+1, M, 3], F [T+1, M, 3, 3], substeps per frame)."""

    loss: float
    grads: dict[str, float]
    flows: list[torch.Tensor]
    trajectory: "Frames"  # noqa: F821  (clflow.mpm.autograd.Frames)

    @property
    def substeps(self) -> int:
        return self.trajectory.substeps


def _parameterizations(cfg: SceneConfig):
    from clflow.mpm.parameterization import parameterization

    names = cfg.optimize.parameters
    if not names:
        raise InputError(f"{cfg.source}: optimize.parameters is empty: name the parameters to optimise")
    return {name: parameterization(cfg.material.type, name) for name in names}


def observed_flow_of(cfg: SceneConfig, prepared: Prepared, frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The guidance video's frames [T+1, H, W, 3] at the simulation's frame times, their
    optical flow [T, H, W, 2] (px per frame) and its confidence [T, H, W] in [0, 1]
    (``flow.confidence``), cached in ``output/observed_flow.npz``."""
    from clflow.flow.optical_flow import observed_confidence, observed_flow
    from clflow.flow.video import read_video

    if cfg.video is None:
        raise InputError(f"{cfg.source}: video is required to optimise (the guidance video or image folder)")
    cam = prepared.camera
    # a video file keeps its own frame rate; an image folder has none: frame k is at k / fps
    video = read_video(cfg.video, fps=cfg.simulation.fps if cfg.video.is_dir() else None)
    times = np.arange(frames + 1) / cfg.simulation.fps
    if video.times is not None and video.times[-1] + 1e-9 < times[-1]:
        raise InputError(f"{cfg.video}: the video lasts {video.times[-1]:.3g} s, the simulation "
                         f"{times[-1]:.3g} s ({frames} frames at {cfg.simulation.fps:g} fps)")
    video = video.resample(times)
    if (video.width, video.height) != (cam.width, cam.height):
        raise InputError(f"{cfg.video}: frames are {video.width}x{video.height} px, the guidance camera "
                         f"{cam.width}x{cam.height}; crop/resize the video (clflow.flow.video.fit_to_camera)")
    cache = cfg.output / "observed_flow.npz"
    key = np.array([cfg.flow.method, cfg.flow.preset, cfg.flow.confidence, str(cfg.video), str(frames)])
    if cache.exists():
        with np.load(cache) as data:
            if data["key"].tolist() == key.tolist():
                return video.frames, data["flow"], data["confidence"]
    estimator = dict(preset=cfg.flow.preset, source=str(cfg.video))
    flow = observed_flow(video.frames, cfg.flow.method, **estimator)
    confidence = observed_confidence(video.frames, flow, cfg.flow.confidence, cfg.flow.method, **estimator)
    with atomic_path(cache) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, flow=flow, confidence=confidence, key=key)
    return video.frames, flow, confidence


def loss_mask(cfg: SceneConfig, prepared: Prepared) -> torch.Tensor:
    """[H, W] bool: where the flow loss is evaluated."""
    import torch.nn.functional as nnf

    cam = prepared.camera
    setting = cfg.flow.mask
    if setting == "none":
        return torch.ones(cam.height, cam.width, dtype=torch.bool)
    if setting == "alpha":  # the object at rest, grown so the moving object stays inside
        with torch.no_grad():
            alpha = render_object_alpha(prepared.obj_rest, cam)
        grow = max(2, min(cam.width, cam.height) // 12)
        grown = nnf.max_pool2d((alpha > 0.5).float()[None, None], 2 * grow + 1, stride=1, padding=grow)[0, 0] > 0
        if not bool(grown.any()):
            raise InputError(f"{cfg.source}: the object is not visible from the guidance camera (empty flow mask)")
        return grown
    from clflow.flow.optical_flow import mask_from_image

    return torch.from_numpy(mask_from_image(setting, cam.width, cam.height))  # a path resolved by the config


def simulated_flows(prepared: Prepared, x: torch.Tensor, F: torch.Tensor, frames: int) -> list[torch.Tensor]:
    """Simulated flow [H, W, 2] of each frame step t -> t+1 for t < frames."""
    scenes = [frame_gaussians(prepared.static, prepared.obj_rest, x[t], F[t]) for t in range(frames + 1)]
    return [render_flow(scenes[t], scenes[t + 1], prepared.camera)[0] for t in range(frames)]


def flow_loss(cfg: SceneConfig, flows, observed: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """The ``flow.loss`` of the simulated flows (T of [H, W, 2]) against ``observed``
    [T, H, W, 2], weighted per pixel by ``weight`` [T, H, W] (the loss mask times the observed
    flow's confidence) and divided by the weight's sum: a weighted per-pixel mean."""
    from clflow.flow.losses import charbonnier_flow_loss, masked_flow_loss

    fn = masked_flow_loss if cfg.flow.loss == "l2" else charbonnier_flow_loss
    return fn(torch.stack(flows).double(), observed, weight)


def horizon(cfg: SceneConfig, iteration: int) -> int:
    """Frames in the loss at ``iteration`` (the horizon curriculum: first frames first)."""
    total, opt = cfg.simulation.frames, cfg.optimize
    if opt.horizon_start <= 0:
        return total
    return min(total, opt.horizon_start + opt.horizon_step * iteration)


def rate_schedule(opt, iteration: int) -> float:
    """Factor on the learning rates at ``iteration``: cosine from 1 down to
    ``optimize.final_rate`` at the last iteration (large steps far from the optimum, small
    ones to settle in it)."""
    progress = iteration / max(1, opt.iterations - 1)
    return opt.final_rate + (1.0 - opt.final_rate) * 0.5 * (1.0 + math.cos(math.pi * progress))


class Optimization:
    """One optimisation run of a config (see module docstring)."""

    def __init__(self, cfg: SceneConfig, *, progress: Callable[[dict], None] | None = None):
        self.cfg = cfg = resolve_material(cfg)
        self.params = _parameterizations(cfg)
        self.progress = progress or (lambda row: None)
        self.prepared = prepare(cfg)
        self.frames = cfg.simulation.frames
        self.mask = loss_mask(cfg, self.prepared)
        self.video_frames, observed, confidence = observed_flow_of(cfg, self.prepared, self.frames)
        self.observed = torch.from_numpy(observed).double()
        self.weight = self.mask * torch.from_numpy(confidence).double()  # [T, H, W] in [0, 1]
        self.checkpoint = cfg.output / "checkpoint.json"

    # -- state ---------------------------------------------------------------------------

    def initial_state(self) -> OptimizerState:
        values, density = material_values(self.cfg)
        values["density"] = density
        z = {n: float(p.encode(values[n])) for n, p in self.params.items()}
        return OptimizerState(0, z, {n: 0.0 for n in z}, {n: 0.0 for n in z})

    def load_state(self) -> OptimizerState:
        try:
            data = json.loads(self.checkpoint.read_text())
            state = OptimizerState(**data["state"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputError(f"cannot resume from {self.checkpoint}: {exc}") from None
        if set(state.z) != set(self.params):
            raise InputError(f"{self.checkpoint} optimises {sorted(state.z)}, the config {sorted(self.params)}")
        return state

    def save_state(self, state: OptimizerState) -> None:
        atomic_write_text(self.checkpoint, json.dumps({"config": str(self.cfg.source), "state": asdict(state)}))

    def values(self, z: dict[str, float]) -> dict[str, float]:
        return {n: float(p.decode(torch.tensor(z[n], dtype=torch.float64))) for n, p in self.params.items()}

    # -- one iteration -------------------------------------------------------------------

    def evaluate(self, z: dict[str, float], frames: int, with_grad: bool = True, min_substeps: int = 1) -> Evaluation:
        """Loss (and dloss/dz) at z over ``frames`` frames."""
        zt = {n: torch.tensor(v, dtype=torch.float64, requires_grad=with_grad) for n, v in z.items()}
        decoded = {n: self.params[n].decode(zt[n]) for n in zt}
        params, density = material_values(self.cfg, {n: float(v.detach()) for n, v in decoded.items()})
        sim = build_simulator(self.cfg, self.prepared.setup, params, density, min_substeps=min_substeps)
        traj = run(sim, frames, decoded)
        flows = simulated_flows(self.prepared, traj.x, traj.F, frames)
        loss = flow_loss(self.cfg, flows, self.observed[:frames], self.weight[:frames])
        if not bool(torch.isfinite(loss.detach())):
            raise FloatingPointError("the flow loss is not finite")
        grads = {}
        if with_grad:
            loss.backward()
            grads = {n: float(zt[n].grad) for n in zt}
            if not all(math.isfinite(g) for g in grads.values()):
                raise FloatingPointError("the gradient is not finite")
        return Evaluation(float(loss.detach()), grads, [f.detach() for f in flows], traj)

    def adam_step(self, state: OptimizerState, grads: dict[str, float]) -> OptimizerState:
        """One Adam step in z, gradient clipped to CLIP_NORM, with adaptive restart
        (O'Donoghue and Candes 2015): when the last step went uphill along the new gradient
        (g . dz > 0), the momentum is dropped, so an overshoot turns back at once instead
        of coasting on for several iterations."""
        norm = math.sqrt(sum(g * g for g in grads.values()))
        scale = min(1.0, CLIP_NORM / norm) if norm > 0 else 1.0
        z, m, v = dict(state.z), dict(state.m), dict(state.v)
        k_m = state.momentum_steps + 1
        if state.history:
            last = state.history[-1]["z"]
            if sum(grads[n] * (z[n] - last[n]) for n in grads) > 0:
                m, k_m = {n: 0.0 for n in m}, 1
        k = state.iteration + 1
        schedule = rate_schedule(self.cfg.optimize, state.iteration)
        for n, g in grads.items():
            g *= scale
            m[n] = BETAS[0] * m[n] + (1 - BETAS[0]) * g
            v[n] = BETAS[1] * v[n] + (1 - BETAS[1]) * g * g
            m_hat, v_hat = m[n] / (1 - BETAS[0] ** k_m), v[n] / (1 - BETAS[1] ** k)
            rate = self.cfg.optimize.learning_rates.get(n, DEFAULT_RATE) * state.step_scale * schedule
            z[n] -= rate * m_hat / (math.sqrt(v_hat) + ADAM_EPS)
        return dataclasses.replace(state, iteration=k, z=z, m=m, v=v, history=list(state.history), momentum_steps=k_m)

    def run(self, resume: bool = False, stop_after: int | None = None) -> OptimizerState:
        """Optimise for ``optimize.iterations`` iterations (``stop_after``: at most this many
        in this call, for tests of resuming); returns the final state."""
        self.cfg.output.mkdir(parents=True, exist_ok=True)
        state = self.load_state() if resume and self.checkpoint.exists() else self.initial_state()
        failures, done_here = 0, 0
        while state.iteration < self.cfg.optimize.iterations and (stop_after is None or done_here < stop_after):
            frames = horizon(self.cfg, state.iteration)
            start = time.perf_counter()
            try:
                result = self.evaluate(state.z, frames, min_substeps=state.substeps)
            except (FloatingPointError, ClflowError) as exc:
                failures += 1
                if failures > MAX_FAILURES or state.iteration == 0 and failures > 1:
                    raise ClflowError(f"optimisation stopped at iteration {state.iteration}: {exc} "
                                      f"({failures} failed attempts); last good parameters: {self.values(state.z)}")
                previous = state.history[-1]["z"] if state.history else state.z
                log.warning("iteration %d failed (%s): back to the last good parameters, half the step, "
                            "momentum dropped", state.iteration, exc)
                state = dataclasses.replace(state, z=dict(previous), m={n: 0.0 for n in state.m},
                                            step_scale=state.step_scale / 2, momentum_steps=0)
                continue
            failures = 0
            row = {"iteration": state.iteration, "loss": result.loss, "frames": frames, "z": dict(state.z),
                   "params": self.values(state.z), "substeps": result.substeps,
                   "seconds": time.perf_counter() - start}
            state = self.adam_step(state, result.grads)
            state.substeps = max(state.substeps, result.substeps)
            state.history.append(row)
            self.save_state(state)
            self.progress(row)
            done_here += 1
        return state

    # -- results -------------------------------------------------------------------------

    def write_results(self, state: OptimizerState) -> dict:
        """params.json, metrics.json, history.json, loss.png and comparison.mp4 in output/."""
        from clflow.flow.metrics import endpoint_error
        from clflow.flow.visualize import comparison_panel, write_video

        out = self.cfg.output
        final = self.values(state.z)
        params, density = material_values(self.cfg, final)
        result = self.evaluate(state.z, self.frames, with_grad=False, min_substeps=state.substeps)
        loss, flows = result.loss, result.flows
        mask = self.mask.numpy()
        epe = float(np.mean([endpoint_error(f.numpy(), self.observed[t].numpy(), mask) for t, f in enumerate(flows)]))
        metrics = {"flow_loss": loss, "epe_px": epe, "iterations": state.iteration,
                   "seconds_per_iteration": float(np.mean([h["seconds"] for h in state.history])) if state.history else 0.0}
        truth = self.cfg.ground_truth
        if truth:
            metrics["relative_error"] = {n: abs(final[n] - truth[n]) / abs(truth[n]) for n in final if n in truth}
        record = {"material": self.cfg.material.type, "parameters": params, "density": density,
                  "optimized": final, "units": {n: parameter_unit(self.cfg, n) for n in final}}
        atomic_write_text(out / "params.json", json.dumps(record, indent=2))
        atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2))
        atomic_write_text(out / "history.json", json.dumps(state.history, indent=1))
        write_history_plot(out / "loss.png", state.history, truth)
        # side by side: guidance | guidance flow | simulated flow | error, plus the simulated frames
        traj = result.trajectory
        sim_frames = render_frames(SimulationResult(self.prepared, params, density, traj.x.detach(), traj.F.detach()))
        max_flow = max(float(self.observed.norm(dim=-1).max()), 1e-6)
        panels = [np.concatenate([comparison_panel(self.video_frames[t], self.observed[t].numpy(), flows[t].numpy(), max_flow),
                                  sim_frames[t]], 1) for t in range(self.frames)]
        write_video(out / "comparison.mp4", np.stack(panels), self.cfg.simulation.fps)
        return metrics


def parameter_unit(cfg: SceneConfig, name: str) -> str:
    """SI unit of an optimised parameter (of a config with a concrete material)."""
    from clflow.materials import DENSITY, get_material

    return DENSITY.unit if name == "density" else get_material(cfg.material.type).param(name).unit


def write_history_plot(path: Path, history: list[dict], truth: dict[str, float]) -> None:
    """PNG: the loss (log scale) and each parameter (log10 of its value) per iteration,
    with the ground truth as a dashed line when known. Drawn with OpenCV."""
    import cv2

    from clflow.flow.visualize import write_image

    names = sorted(history[0]["params"]) if history else []
    panels = [("flow loss (log10)", [math.log10(max(h["loss"], 1e-30)) for h in history], None)]
    for n in names:
        t = math.log10(truth[n]) if n in truth and truth[n] > 0 else None
        panels.append((f"log10 {n}", [math.log10(max(h["params"][n], 1e-30)) for h in history], t))
    width, height = 420, 220
    images = []
    for title, values, target in panels:
        img = np.full((height, width, 3), 255, np.uint8)
        cv2.putText(img, title, (10, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        if values:
            lo, hi = min(values + ([target] if target is not None else [])), max(values + ([target] if target is not None else []))
            span = hi - lo or 1.0
            to_px = lambda i, y: (int(40 + (width - 60) * i / max(1, len(values) - 1)),  # noqa: E731
                                  int(height - 30 - (height - 60) * (y - lo) / span))
            cv2.rectangle(img, (40, 30), (width - 20, height - 30), (200, 200, 200), 1)
            if target is not None:
                y = to_px(0, target)[1]
                for x0 in range(40, width - 20, 12):
                    cv2.line(img, (x0, y), (min(x0 + 6, width - 20), y), (0, 160, 0), 1)
            pts = np.array([to_px(i, y) for i, y in enumerate(values)], np.int32)
            cv2.polylines(img, [pts], False, (200, 60, 30), 2, cv2.LINE_AA)
            cv2.putText(img, f"{hi:.3g}", (2, 36), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
            cv2.putText(img, f"{lo:.3g}", (2, height - 30), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        images.append(img)
    write_image(path, np.concatenate(images, 0))


__all__ = ["Optimization", "OptimizerState", "horizon", "parameter_unit", "rate_schedule", "write_history_plot"]
