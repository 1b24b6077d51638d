"""Checks before a long run starts, so a bad input fails in seconds with its numbers instead
of running for hours or ending with a wrong result.

- :func:`plan_run`: the substeps per frame the material needs, a timing of one substep, the
  predicted time, and the refusal of a run beyond ``simulation.max_substeps``
  (``--max-substeps``) with the ways out.
- :func:`check_guidance`: the guidance video shows the object the config describes: the
  object covers a reasonable part of the image, the video's first frame looks like the
  scene rendered from the guidance camera, and the observed flow has structure (motion above
  the noise level, confident pixels) inside the loss mask.

Limits and how to raise them: docs/pipeline.md, "Pre-flight checks".
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from clflow.errors import InputError
from clflow.limits import format_duration
from clflow.mpm import StabilityWarning
from clflow.pipeline.simulation import (
    SubstepLimitError,
    build_simulator,
    substep_limit_message,
    unstable_start,
)
from clflow.scene.config import SceneConfig

log = logging.getLogger(__name__)

# guidance checks (measured on the demo, a grey, a noise video and wrong cameras: docs/pipeline.md)
MIN_COVERAGE = 0.002  # the object at rest covers at least this fraction of the image...
MIN_COVERAGE_PX = 16  # ...and this many pixels
MAX_COVERAGE = 0.9  # beyond it the camera is likely inside the object
MIN_APPEARANCE = 0.3  # correlation of the video's first frame with the rendered scene inside the mask
MIN_MOTION_PX = 0.1  # the 95th percentile of the observed flow inside the mask (px per frame)
MIN_CONFIDENT = 0.2  # fraction of mask pixels whose flow confidence is above 0.5
# the simulated flow at the start against the observed one over the first AGREEMENT_FRAMES frame
# steps (weighted cosine): below this it points against it (a camera on the other side, a mirrored video)
MIN_AGREEMENT = 0.0
AGREEMENT_FRAMES = 3


@dataclass(frozen=True)
class RunPlan:
    """What one simulation of a config will cost."""

    substeps: int  # per frame
    dt: float  # s
    limit: str  # what limits dt
    particles: int
    frames: int
    seconds_per_substep: float
    render_seconds_per_frame: float = 0.0  # the flow's rendering and loss, forward and backward, every view

    @property
    def forward_seconds(self) -> float:
        return self.frames * self.substeps * self.seconds_per_substep

    def seconds(self, gradient: bool) -> float:
        """The predicted seconds of a run (``gradient``: an iteration, adjoint and rendering included)."""
        if not gradient:
            return self.forward_seconds
        return self.forward_seconds * GRADIENT_COST + self.frames * self.render_seconds_per_frame


# an iteration with gradients costs about this many forward runs: the forward, then the adjoint
# with its replay at 2.0-2.6x a forward run (docs/history/benchmarks-2026-11.md, "MPM adjoint")
GRADIENT_COST = 3.0


def plan_run(
    cfg: SceneConfig,
    setup,
    values,
    *,
    frames: int | None = None,
    min_substeps: int = 1,
    max_substeps: int | None = None,
    dtype: torch.dtype = torch.float32,
    optimizing: bool = False,
    time_scale: float = 1.0,
) -> RunPlan:
    """The substeps of a run of the config's objects, each with its ObjectValues
    (``values``), and the seconds one substep takes (two substeps timed on a throwaway
    simulator); SubstepLimitError (the numbers and the ways out) beyond ``max_substeps``,
    InputError for a fixed ``simulation.substep_dt`` above the stable step of these values
    (``optimizing``: the message says the optimiser would reject every such run);
    ``time_scale``: simulated seconds per video second (clflow.pipeline.simulation.build_simulator)."""
    with warnings.catch_warnings():  # an unstable fixed step is refused below, with the config key
        warnings.simplefilter("ignore", StabilityWarning)
        sim = build_simulator(cfg, setup, values, dtype=dtype, min_substeps=min_substeps, time_scale=time_scale)
    stable = sim.limit_reason(sim.state.v)
    limit = stable if cfg.simulation.substep_dt is None else f"simulation.substep_dt; stable: {stable}"
    if max_substeps is not None and sim.substeps > max_substeps:
        sim.step()  # a timing for the message: the one substep is cheap next to the refused run
        sim.device.finish()
        start = time.perf_counter()
        sim.step()
        sim.device.finish()  # a substep only enqueues its kernels
        raise SubstepLimitError(
            substep_limit_message(cfg, sim.substeps, sim.dt, limit, max_substeps, time.perf_counter() - start)
        )
    unstable = unstable_start(sim)  # only a fixed substep_dt can be
    if unstable:
        why = "the optimiser rejects unstable runs" if optimizing else "the run would blow up or break the CFL limit"
        raise InputError(
            f"{cfg.source}: simulation.substep_dt = {cfg.simulation.substep_dt:.3g} s is {unstable}; {why}: "
            f"use substep_dt: auto or a shorter one"
        )
    sim.step()  # the first substep may build kernels
    sim.device.finish()
    start = time.perf_counter()
    sim.step()
    sim.step()
    sim.device.finish()  # a substep only enqueues its kernels
    seconds = (time.perf_counter() - start) / 2
    return RunPlan(sim.substeps, sim.dt, limit, sim.n, cfg.simulation.frames if frames is None else frames, seconds)


def describe(plan: RunPlan, what: str, gradient: bool) -> str:
    """One line: substeps, dt and the predicted time of a run (``gradient``: per iteration)."""
    seconds = plan.seconds(gradient)
    return (
        f"{what}: {plan.substeps} substeps per frame (dt = {plan.dt:.3g} s, limited by {plan.limit}), "
        f"{plan.particles:,} particles, {plan.frames} frames: about {format_duration(seconds)}"
        f"{' per iteration' if gradient else ''} ({1e3 * plan.seconds_per_substep:.3g} ms per substep)"
    )


# -- the guidance video -------------------------------------------------------------------------


@dataclass(frozen=True)
class GuidanceCheck:
    """The measured numbers of one guidance view."""

    coverage: float  # fraction of the image the object covers at rest (alpha > 0.5)
    coverage_px: int
    appearance: float  # correlation of the video's frame 0 with the rendered scene inside the mask
    motion_px: float  # 95th percentile of the observed flow's length inside the mask (px per frame)
    confident: float  # fraction of mask pixels (over all frame steps) with confidence > 0.5
    # weighted cosine of the simulated flow at the start and the observed flow, first frames (None: not measured)
    agreement: float | None = None

    def problems(self) -> list[str]:
        out = []
        if self.coverage < MIN_COVERAGE or self.coverage_px < MIN_COVERAGE_PX:
            out.append(
                f"the object covers {100 * self.coverage:.2g} % of the image ({self.coverage_px} px; at "
                f"least {100 * MIN_COVERAGE:g} % and {MIN_COVERAGE_PX} px needed)"
            )
        if self.coverage > MAX_COVERAGE:
            out.append(
                f"the object covers {100 * self.coverage:.3g} % of the image (more than "
                f"{100 * MAX_COVERAGE:g} %: is the camera inside the object?)"
            )
        if self.appearance < MIN_APPEARANCE:
            out.append(
                f"the video's first frame does not look like the scene rendered from the camera inside the "
                f"loss mask (correlation {self.appearance:.2f}, at least {MIN_APPEARANCE:g} needed: a wrong "
                f"camera or video?)"
            )
        if self.motion_px < MIN_MOTION_PX:
            out.append(
                f"the video shows no motion inside the loss mask (95th percentile of the flow "
                f"{self.motion_px:.3g} px per frame, at least {MIN_MOTION_PX:g} needed)"
            )
        if self.confident < MIN_CONFIDENT:
            out.append(
                f"the observed flow is unreliable inside the loss mask ({100 * self.confident:.2g} % of its "
                f"pixels have confidence > 0.5, at least {100 * MIN_CONFIDENT:g} % needed: noise?)"
            )
        if self.agreement is not None and self.agreement < MIN_AGREEMENT:
            out.append(
                f"the simulated motion at the starting parameters points against the video's over the first "
                f"{AGREEMENT_FRAMES} frames (cosine {self.agreement:.2f}; is the camera on the other side of "
                f"the object, or the video mirrored?)"
            )
        return out

    def record(self) -> dict:
        return {
            "coverage": self.coverage,
            "coverage_px": self.coverage_px,
            "appearance": self.appearance,
            "motion_px": self.motion_px,
            "confident": self.confident,
            "agreement": self.agreement,
        }


def flow_agreement(simulated: list[torch.Tensor], observed: torch.Tensor, weight: torch.Tensor) -> float:
    """Cosine of simulated flows (T of [H, W, 2]) and ``observed`` [>= T, H, W, 2], each pixel
    weighted by ``weight`` [>= T, H, W]; 0 when either has no motion."""
    sim = torch.stack(simulated).double()
    obs, w = observed[: len(simulated)].double(), weight[: len(simulated), ..., None].double()
    norm = math.sqrt(float((sim * sim * w).sum()) * float((obs * obs * w).sum()))
    return float((sim * obs * w).sum()) / norm if norm > 1e-30 else 0.0


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two equally long vectors; 0 when either is constant."""
    a, b = a - a.mean(), b - b.mean()
    norm = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / norm if norm > 1e-12 else 0.0


def measure_view(
    prepared, camera, mask: torch.Tensor, video_frames: np.ndarray, flow: np.ndarray, confidence: np.ndarray
) -> GuidanceCheck:
    """The numbers of :class:`GuidanceCheck` for one view: ``mask`` [H, W] the loss mask,
    ``video_frames`` [T+1, H, W, 3] uint8, ``flow`` [T, H, W, 2], ``confidence`` [T, H, W]."""
    from clflow.media import to_uint8
    from clflow.pipeline.render import render_object_alpha, render_rgb
    from clflow.splat.gaussians import Gaussians

    with torch.no_grad():
        alpha = render_object_alpha(prepared.obj_rest, camera)
        rendered = to_uint8(render_rgb(Gaussians.cat([prepared.obj_rest, prepared.static]), camera))
    covered = int((alpha > 0.5).sum())
    m = mask.numpy().astype(bool)
    grey = lambda img: img.astype(np.float64).mean(-1)  # noqa: E731
    appearance = _correlation(grey(rendered)[m], grey(video_frames[0])[m]) if m.any() else 0.0
    speeds = np.linalg.norm(flow, axis=-1)[:, m]
    motion = float(np.percentile(speeds, 95)) if speeds.size else 0.0
    confident = float((confidence[:, m] > 0.5).mean()) if speeds.size else 0.0
    return GuidanceCheck(covered / alpha.numel(), covered, appearance, motion, confident)


def check_guidance(cfg: SceneConfig, checks: list[GuidanceCheck], force: bool) -> list[str]:
    """InputError naming every problem of the guidance views (their measured numbers), unless
    ``force``: then each problem is logged as a warning and returned (for metrics.json)."""
    problems = []
    for i, check in enumerate(checks):
        where = f"guidance view {i}: " if len(checks) > 1 else ""
        problems += [where + p for p in check.problems()]
    if problems and not force:
        raise InputError(
            f"{cfg.source}: the guidance video does not fit the scene: {'; '.join(problems)}; "
            f"check camera and video, or optimise anyway with --force-video"
        )
    for p in problems:
        log.warning("guidance check failed (forced with --force-video): %s; the result is likely wrong", p)
    return problems


__all__ = [
    "flow_agreement",
    "GuidanceCheck",
    "RunPlan",
    "check_guidance",
    "describe",
    "measure_view",
    "plan_run",
]
