"""The objective of an optimisation: the flow loss at a point of the parameters, and the
calibration of the flow estimator's error it compares against."""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import warnings
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from clflow.errors import ClflowError
from clflow.fileio import atomic_path
from clflow.flow.scene_flow import FlowReader, flows_of, render_scene_flows
from clflow.mpm import StabilityWarning
from clflow.pipeline.fit.population import RunPoint, evaluate_in_populations, populations_pay, run_point
from clflow.pipeline.fit.problem import Problem
from clflow.pipeline.fit.state import Evaluation, OptimizerState, UnstableRun
from clflow.pipeline.render import render_rgb_frames
from clflow.pipeline.simulation import build_simulator, scene_run_values
from clflow.scene.config import TIME_SCALE, SceneConfig
from clflow.splat.device_scene import DeviceScene

log = logging.getLogger(__name__)

LM_STEP = 0.01  # Levenberg-Marquardt's finite-difference step in z (a 2.3 % change of a log-scale parameter)

# flow.bias_correction renders the simulation at this many times the guidance camera's pixels
# per side and area-averages them, since a camera's pixel integrates light over its area
# (DIS's error depends on that blur: docs/flow.md)
SUPERSAMPLE = 2
# Levenberg-Marquardt's last word (Steps.own_loss_line_search) and the result's own loss take
# the estimator's error as the mean of its answers over these whole-pixel shifts (dx, dy) of
# the camera, from one rendering JITTER_MARGIN px wider on each side (no resampling): one
# answer jumps between nearby points (DIS's patch grid is fixed to the image corner;
# docs/pipeline.md, "Why the sand stops short"), the mean is smooth. Every residue mod 4 twice per axis, each parity pair (dx, dy mod 2) twice, the
# mean shift zero.
# The iterations before keep one answer (ONE_SHIFT), at an eighth of the estimator's cost.
JITTER_SHIFTS = ((0, 0), (0, -3), (1, 2), (-3, -1), (-2, -2), (2, 3), (-1, 0), (3, 1))
ONE_SHIFT = ((0, 0),)


def simulated_view_flows(scene: DeviceScene, traj, frames: int, cameras: list) -> list[list[torch.Tensor]]:
    """Simulated flows [H, W, 2] of each frame step t -> t+1 (t < frames) of the run ``traj``
    (clflow.mpm.Frames: x [>= frames + 1, M, 3], F, its states on the device where it has them)
    on ``scene`` seen by each of ``cameras``."""
    x, F = traj.x[: frames + 1], traj.F[: frames + 1]
    states = None if traj.states is None else traj.states[: frames + 1]
    return [render_scene_flows(scene, x, F, cam, states=states) for cam in cameras]


def flow_loss(cfg: SceneConfig, flows, observed: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """The ``flow.loss`` of the simulated flows (T of [H, W, 2]) against ``observed``
    [T, H, W, 2], weighted per pixel by ``weight`` [T, H, W] (the loss mask times the observed
    flow's confidence) and divided by the weight's sum: a weighted per-pixel mean."""
    from clflow.flow.losses import charbonnier_flow_loss, masked_flow_loss

    fn = masked_flow_loss if cfg.flow.loss == "l2" else charbonnier_flow_loss
    return fn(torch.stack(flows).double(), observed, weight)


class Objective:
    """The loss of a :class:`~clflow.pipeline.fit.problem.Problem` at a point z: simulate,
    render each view's flow, compare with the observed flow less the flow estimator's own
    error (the calibration, ``flow.bias_correction``); the residuals and their Jacobian for
    Levenberg-Marquardt.

    The calibration is this objective's state: ``errors``, each view's estimator error
    [T, H, W, 2] (None before any), measured at ``OptimizerState.calibrated_at`` and saved in
    ``calibration_file`` (a search start's polish has an objective, and a file, of its own).
    The last two Jacobians are cached (the best point's and the last step's)."""

    def __init__(self, problem: Problem, calibration_file: Path):
        self.problem = problem
        self.calibration_file = calibration_file
        self.errors: list[torch.Tensor | None] = [None] * len(problem.views)
        # (z, frames, variables, grid, substeps) -> (Evaluation, J)
        self._lm_cache: dict[tuple, tuple[Evaluation, torch.Tensor]] = {}

    def fork(self, calibration_file: Path) -> Objective:
        """This objective with a calibration of its own (none measured yet; saved in
        ``calibration_file``) and no cached Jacobians: a search start's polish's."""
        other = copy.copy(self)
        other.calibration_file, other.errors, other._lm_cache = calibration_file, [None] * len(self.errors), {}
        return other

    def target(self, view: int) -> torch.Tensor:
        """[T, H, W, 2] what the simulated flow of guidance view ``view`` is fitted to: the
        observed flow less the estimator's error measured on the simulation (the observed
        flow itself before any)."""
        observed, error = self.problem.views[view].observed, self.errors[view]
        return observed if error is None else observed - error

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
        variables = self.problem.variables if variables is None else variables
        grid = self.problem.model_grid if grid is None else grid
        point = self._point(z, grid, min_substeps, grads_of=variables if with_grad else ())
        reader = FlowReader(self.problem.scene_on_device(grid), [view.camera for view in self.problem.views])
        traj, read = run_point(point, frames, reader)
        return self._evaluation(point, traj, frames, read)

    def _point(self, z: dict[str, float], grid: int, min_substeps: int, grads_of: tuple[str, ...] = ()) -> RunPoint:
        """What a run at z on the grid of ``grid`` nodes takes: its simulator (built, not run)
        and the inputs of clflow.pipeline.simulation.run, with z's ``grads_of`` requiring grad."""
        prepared = self.problem.prepared_on(grid)
        zt = {n: torch.tensor(v, dtype=torch.float64, requires_grad=n in grads_of) for n, v in z.items()}
        decoded = {n: p.decode(zt[n]) for n, p in self.problem.params.items()}
        velocity = self.problem.velocity_input(zt, prepared)
        shared = velocity is not None and velocity.dim() == 1  # every object's velocity, a tensor [3]
        speeds = (velocity,) * len(self.problem.cfg.objects) if shared else self.problem.velocities(z)
        objects = self.problem.object_values({n: float(v.detach()) for n, v in decoded.items()}, speeds)
        scale = self.problem.time_scale(z)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StabilityWarning)
            sim = build_simulator(
                self.problem.cfg,
                prepared.setup,
                objects,
                min_substeps=min_substeps,
                max_substeps=self.problem.cfg.simulation.max_substeps,
                time_scale=scale,
            )
        # several objects: each parameter per particle, its object's particles alone (the
        # time scale is the simulator's frame step, no material's: its Jacobian column is LM's
        # finite difference, never a gradient)
        material = {n: v for n, v in decoded.items() if n != TIME_SCALE.name}
        run_values = scene_run_values(self.problem.cfg, prepared.setup, objects, material)
        return RunPoint(zt, grads_of, grid, prepared, objects, sim, run_values, velocity, scale)

    def _evaluation(self, point: RunPoint, traj, frames: int, read: tuple | None = None) -> Evaluation:
        """The Evaluation of ``point``'s run ``traj`` (Frames), its gradients where it asked for
        them; ``read``: what the run's FlowReader gave (each view's features and transmittance,
        rendered in the run's op), else the flows are rendered here."""
        sim = point.sim
        needed = sim.stable_substeps()
        if traj.substeps < needed:  # a fixed simulation.substep_dt too long for these parameters
            raise UnstableRun(
                f"dt = {sim.frame_dt / traj.substeps:.3g} s exceeds the stable step "
                f"{sim.frame_dt / needed:.3g} s of these parameters ({sim.limit_reason(sim.state.v)})"
            )
        if traj.unstable:  # finished, but not a run to learn from
            raise UnstableRun(traj.unstable)
        cameras = [v.camera for v in self.problem.views]
        if read is None:
            flows, *more_flows = simulated_view_flows(self.problem.scene_on_device(point.grid), traj, frames, cameras)
        else:
            flows, *more_flows = [flows_of(read[2 * k], read[2 * k + 1]) for k in range(len(cameras))]
        loss = self.loss_of([flows, *more_flows])
        if not bool(torch.isfinite(loss.detach())):
            raise FloatingPointError("the flow loss is not finite")
        grads = {}
        if point.grads_of:
            loss.backward()
            grads = {n: float(point.zt[n].grad) for n in point.grads_of}
            if not all(math.isfinite(g) for g in grads.values()):
                raise FloatingPointError("the gradient is not finite")
        return Evaluation(
            float(loss.detach()),
            grads,
            [f.detach() for f in flows],
            traj,
            point.grid,
            tuple([f.detach() for f in view] for view in more_flows),
        )

    def evaluate_batch(
        self,
        points: list[dict[str, float]],
        frames: int,
        *,
        min_substeps: int | list[int] = 1,
        grid: int | None = None,
    ) -> Iterator[Evaluation | Exception]:
        """Forward-only evaluations of independent ``points`` (z dicts), yielded in order, each
        what ``evaluate(z, frames, with_grad=False, min_substeps=..., grid=...)`` gives
        (``min_substeps``: every point's, or a list of each point's); a
        point whose run fails (FloatingPointError, ClflowError: an unstable run, a substep
        limit) yields its error instead, so that one failing point loses none of the others.

        Where populations pay (clflow.pipeline.fit.population: the GPU plan) the points are
        simulated together as populations, all before the first is yielded. Elsewhere they
        are simulated one after another, each when the consumer asks for it: one that stops
        iterating (a budget spent, a failed column) simulates no more."""
        substeps = min_substeps if isinstance(min_substeps, list) else [min_substeps] * len(points)
        if populations_pay() and len(points) > 1:
            grid = self.problem.model_grid if grid is None else grid
            yield from evaluate_in_populations(self, points, frames, substeps, grid)
            return
        for z, least in zip(points, substeps):
            try:
                result = self.evaluate(z, frames, with_grad=False, min_substeps=least, grid=grid)
            except (FloatingPointError, ClflowError) as exc:
                result = exc
            yield result

    def estimator_errors(
        self, result: Evaluation, frames: int, shifts: tuple[tuple[int, int], ...] = ONE_SHIFT
    ) -> list[torch.Tensor]:
        """The flow estimator's error [frames, H, W, 2] in each guidance view on the simulation
        ``result`` (its first ``frames`` frames): the simulation rendered from the view's camera
        (SUPERSAMPLE^2 samples per pixel, area-averaged), its flow estimated with the settings
        that made the observed flow, less the exact simulated flow. ``shifts``: the estimate
        is the mean over these whole-pixel shifts of the camera (JITTER_SHIFTS; one rendering
        that much wider, clflow.flow.optical_flow.shift_mean_flow)."""
        from clflow.flow.optical_flow import observed_flow, shift_mean_flow

        def estimate(video: np.ndarray) -> np.ndarray:
            return observed_flow(
                video, self.problem.cfg.flow.method, preset=self.problem.cfg.flow.preset, source="the simulation"
            )

        margin = max(max(abs(dx), abs(dy)) for dx, dy in shifts)
        traj = result.trajectory
        if traj.states is None:
            x, F, states = traj.x[: frames + 1].detach(), traj.F[: frames + 1].detach(), None
        else:  # x and F on the device, never read to the host
            x, F, states = None, None, traj.states[: frames + 1]
        errors, scene = [], self.problem.scene_on_device(self.problem.model_grid)
        for view, flows in zip(self.problem.views, [result.flows, *result.more_flows]):
            wide = render_rgb_frames(scene, x, F, view.camera.widened(margin), states=states, supersample=SUPERSAMPLE)
            estimated = shift_mean_flow(wide, margin, shifts, estimate)
            errors.append(torch.from_numpy(estimated).double() - torch.stack(flows[:frames]).double())
        return errors

    def calibrate(
        self,
        state: OptimizerState,
        result: Evaluation,
        frames: int,
        shifts: tuple[tuple[int, int], ...] = ONE_SHIFT,
        errors: list[torch.Tensor] | None = None,
    ) -> OptimizerState:
        """Keep the flow estimator's error on the simulation ``result`` (at state.z, its first
        ``frames`` frames; over ``shifts`` as :meth:`estimator_errors`) as each view's
        error (``errors``, saved in ``calibration_file``). The loss then compares
        the simulated flow with the observed flow less that error, so the estimator's
        systematic error (DIS blends a moving object with its background, docs/flow.md)
        cancels instead of biasing the parameters. ``errors``: that error, already measured."""
        calibrated_at = {"z": dict(state.z), "frames": frames, "grid": result.grid}
        if shifts != ONE_SHIFT:
            calibrated_at["shifts"] = [list(shift) for shift in shifts]
        if state.calibrated_at == calibrated_at:  # back at the point measured last (a rejected step)
            return state
        measured = self.estimator_errors(result, frames, shifts) if errors is None else errors
        full_errors = []
        for view, kept, error in zip(self.problem.views, self.errors, measured):
            full = torch.zeros_like(view.observed) if kept is None else kept.clone()
            full[:frames] = error
            full_errors.append(full.numpy())
        self.set_estimator_errors(full_errors)
        self.save_calibration(calibrated_at)
        return dataclasses.replace(state, calibrated_at=calibrated_at)

    def set_estimator_errors(self, errors: list[np.ndarray] | None) -> None:
        """Each view's estimator error [T, H, W, 2] (None: none), the cached evaluations rescored."""
        views = self.problem.views
        self.errors = [None] * len(views) if errors is None else [torch.as_tensor(e).clone() for e in errors]
        self._lm_cache = {key: (self.rescored(cached), J) for key, (cached, J) in self._lm_cache.items()}

    def restore_estimator_errors(self, calibrated_at: dict | None, errors: list | None) -> None:
        """Each view's estimator error back to ``errors`` (as measured at ``calibrated_at``),
        saved again as the calibration file's content."""
        self.set_estimator_errors(None if errors is None or errors[0] is None else errors)
        if calibrated_at is not None:
            self.save_calibration(calibrated_at)

    def save_calibration(self, calibrated_at: dict) -> None:
        """The views' estimator errors, measured at ``calibrated_at``, into ``calibration_file``."""
        with atomic_path(self.calibration_file) as tmp, open(tmp, "wb") as fh:
            np.savez(
                fh,
                key=np.array(json.dumps(calibrated_at, sort_keys=True)),
                **{f"view_{i}": error.numpy() for i, error in enumerate(self.errors)},
            )

    def restore_calibration(self, state: OptimizerState) -> None:
        """Each view's estimator error as it was when ``state`` was saved (on --resume): from
        output/estimator_error.npz, or measured again at ``state.calibrated_at``."""
        key = json.dumps(state.calibrated_at, sort_keys=True)
        try:
            with np.load(self.calibration_file, allow_pickle=False) as data:
                if str(data["key"]) == key:
                    self.set_estimator_errors([data[f"view_{i}"] for i in range(len(self.problem.views))])
                    return
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):  # none, an older one, or damaged
            pass
        log.info("measuring the flow estimator's error again at the checkpoint's calibration point")
        z, frames = state.calibrated_at["z"], state.calibrated_at["frames"]
        grid = state.calibrated_at.get("grid", self.problem.model_grid)
        shifts = tuple(tuple(shift) for shift in state.calibrated_at.get("shifts", ONE_SHIFT))
        at = dataclasses.replace(state, z=dict(z), calibrated_at=None)  # measured there, whatever state.z is now
        result = self.evaluate(z, frames, with_grad=False, min_substeps=state.substeps, grid=grid)
        self.calibrate(at, result, frames, shifts)

    def loss_of(self, view_flows: list[list[torch.Tensor]], errors: list[torch.Tensor] | None = None) -> torch.Tensor:
        """The flow loss of each view's simulated flows (T of [H, W, 2]) against its target (or
        against its observed flow less ``errors``, the estimator's error per view), the mean
        over views."""
        if errors is None:
            targets = [self.target(k) for k in range(len(self.problem.views))]
        else:
            targets = [view.observed[: len(error)] - error for view, error in zip(self.problem.views, errors)]
        return sum(
            flow_loss(self.problem.cfg, flows, target[: len(flows)], view.weight[: len(flows)])
            for flows, target, view in zip(view_flows, targets, self.problem.views)
        ) / len(self.problem.views)

    def self_consistent_loss(
        self, result: Evaluation, frames: int, shifts: tuple[tuple[int, int], ...] = ONE_SHIFT
    ) -> float:
        """``result``'s loss against the observed flow less the estimator's error on ``result``'s
        own simulation (over ``shifts``, :meth:`estimator_errors`): the video's estimated flow
        against the simulation's, estimated alike (with flow.bias_correction; else its loss)."""
        if not self.problem.corrects_bias:
            return result.loss
        errors = self.estimator_errors(result, frames, shifts)
        return float(self.loss_of([result.flows, *result.more_flows], errors))

    @property
    def final_shifts(self) -> tuple[tuple[int, int], ...]:
        """The camera shifts of the estimator's error that scores the result (its final point's
        calibration): JITTER_SHIFTS after Levenberg-Marquardt, whose last word is the line
        search of that smooth own-calibration loss; else ONE_SHIFT, as every iteration's."""
        return JITTER_SHIFTS if self.problem.cfg.optimize.method == "levenberg_marquardt" else ONE_SHIFT

    def rescored(self, result: Evaluation) -> Evaluation:
        """``result`` with its loss against the current targets (after a calibration)."""
        return dataclasses.replace(result, loss=float(self.loss_of([result.flows, *result.more_flows])))

    def residuals(self, flows: list[torch.Tensor], more_flows: tuple[list[torch.Tensor], ...] = ()) -> torch.Tensor:
        """[R] float64 flow residuals whose sum of squares is the l2 flow loss of ``flows``
        (simulated [H, W, 2] per frame step; ``more_flows`` those of views 1..), weighted by
        mask x confidence like the loss."""
        parts = []
        for k, (view_flows, view) in enumerate(zip([flows, *more_flows], self.problem.views)):
            weight = view.weight[: len(view_flows)]  # [T, H, W]
            root = (weight / weight.sum() / len(self.problem.views)).sqrt()[..., None]
            target = self.target(k)
            parts += [((f.double() - target[t]) * root[t])[weight[t] > 0].reshape(-1) for t, f in enumerate(view_flows)]
        return torch.cat(parts)

    def residual_frames(self, steps: int) -> torch.Tensor:
        """[R] int64: the frame step (0..steps-1) of each entry of :meth:`residuals` for
        ``steps`` simulated frame steps per view; a step's residuals in every view share it."""
        parts = []
        for view in self.problem.views:
            inside = (view.weight[:steps] > 0).reshape(steps, -1).sum(1)  # pixels, each (u, v)
            parts += [torch.full((2 * int(n),), t, dtype=torch.int64) for t, n in enumerate(inside)]
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
        points = [{**z, name: z[name] - LM_STEP} for name in variables]
        columns = []
        for nearby in self.evaluate_batch(points, frames, min_substeps=base.substeps, grid=grid):
            if isinstance(nearby, Exception):
                raise nearby
            columns.append((r0 - self.residuals(nearby.flows, nearby.more_flows)) / LM_STEP)
        J = torch.stack(columns, 1)
        # kept under the substeps the run used: a revisit asks for those (a retried run restarts
        # from frame 0 at the raised count, so it equals a run asked for that count)
        used = (*key[:4], base.substeps)
        self._lm_cache = {**dict(list(self._lm_cache.items())[-1:]), used: (base, J)}
        return base, J

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
                    for view_flows, view in zip([flows, *more_flows], self.problem.views)
                ]
            )
        )

    def unexplained_motion(self, result: Evaluation) -> dict[str, float]:
        """How much of the observed motion the simulation ``result`` leaves unexplained: the
        mean squared flow residual against the targets (``residual_px2``, weighted per pixel
        as the loss, over every frame of every view) as a ``fraction`` of the observed flow's
        own mean square (``still_px2``, the residual of a scene that does not move). An l2
        ratio whatever ``flow.loss`` is."""
        from clflow.flow.losses import masked_flow_loss

        residual = still = total_weight = 0.0
        for k, (view, view_flows) in enumerate(zip(self.problem.views, [result.flows, *result.more_flows])):
            simulated, T = torch.stack(view_flows).double(), len(view_flows)
            weight = float(view.weight[:T].sum())  # each view's mean counted by its weight
            residual += weight * float(masked_flow_loss(simulated, self.target(k)[:T], view.weight[:T]))
            still += weight * float(masked_flow_loss(torch.zeros_like(simulated), view.observed[:T], view.weight[:T]))
            total_weight += weight
        return {
            "residual_px2": residual / total_weight,
            "still_px2": still / total_weight,
            "fraction": residual / still if still > 0 else 0.0,
        }
