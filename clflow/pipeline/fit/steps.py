"""Steps of an optimisation: Levenberg-Marquardt with a trust region, Adam, the boxes they stay
in, the horizon curriculum and the learning-rate schedule."""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Callable

import torch

from clflow.errors import ClflowError
from clflow.mpm.parameterization import clip_factor
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.state import LM_DAMPING, Evaluation, OptimizerState
from clflow.scene.config import SceneConfig, is_velocity_component

log = logging.getLogger(__name__)

BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
# per iteration, in z units: a decade per 10 steps for log parameters, a fortieth of the
# typical range (nu 0.012, phi 1.1 deg) near its middle for bounded ones
DEFAULT_RATE = 0.1
DEFAULT_VELOCITY_RATE = 0.1  # m/s per iteration for each velocity component
CLIP_NORM = 10.0  # gradient clipping in z space
# Levenberg-Marquardt (optimize.method: levenberg_marquardt)
LM_MAX_STEP = 1.0  # longest step in z (a decade of a log-scale parameter)
LM_TOLERANCE = 1e-3  # converged when an accepted step moves every variable less (0.23 % of a log-scale one)
LM_GAIN_TOLERANCE = 1e-3  # ... or when the Gauss-Newton model promises less than this fraction of the loss
# the line search of the own-calibration loss after Levenberg-Marquardt stops (line_search):
LINE_STEP = 0.05  # z: the width of its difference quotients (over LM_STEP's 0.01 the estimator's noise swamps them)
LINE_GAIN = 1e-3  # it moves only to a point that lowers the loss by at least this fraction
LINE_GROWTH = 2.0  # each point along the direction this many times as far as the last
LINE_MAX_GROWTH = 6  # points along the direction at most, before the two inside the bracket
# ... and it searches again from the point it moved to, at most this many times in all: one
# search ends at the first bump of the estimator's remaining noise (the trophy: 37.2 -> 38.1
# deg, its loss still falling to 39-40)
LINE_ROUNDS = 4


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


def learning_rate(cfg: SceneConfig, name: str) -> float:
    """Learning rate of the z variable ``name`` per iteration (before the schedule): the
    config's, else DEFAULT_VELOCITY_RATE (m/s) for a velocity component and DEFAULT_RATE."""
    rates = cfg.optimize.learning_rates
    if is_velocity_component(name):  # the rate of velocity (OBJECT.velocity) serves each component
        return rates.get(name.rpartition("_")[0], DEFAULT_VELOCITY_RATE)
    return rates.get(name, DEFAULT_RATE)


def line_search(
    loss: Callable[[dict[str, float]], float],
    z0: dict[str, float],
    f0: float,
    A: torch.Tensor,
    damping: float,
    variables: tuple[str, ...],
    step_of: Callable[[torch.Tensor, torch.Tensor, dict[str, float]], torch.Tensor],
    max_step: float = LM_MAX_STEP,
    g_lm: torch.Tensor | None = None,
    box: dict[str, tuple[float, float]] | None = None,
) -> dict:
    """A line search of ``loss`` (z -> float, inf where the run fails) from z0 (its loss f0)
    along the damped Gauss-Newton direction (A + damping diag A) dz = -g, A = J^T J.

    g (J^T r of the residuals whose sum of squares is the loss) comes from difference
    quotients LINE_STEP wide, (f1 - f0) / 2h per variable, not from J^T r0: with the bias
    correction each point's residuals carry the estimator's noise, which J holds too, so
    J^T r0 points back towards LM's last neighbour. Each difference is taken on the side
    that LM's own J^T r0 (``g_lm``; None: +h) calls downhill, unless that leaves ``box``
    ({name: (lower, upper)} in z). ``step_of(M, g, z)`` solves M dz = -g (the box's edges
    held: Steps.bounded_step). Points go out along the direction, LINE_GROWTH times farther
    each from LINE_STEP at least, while the loss falls (never beyond ``max_step`` from z0, at
    most LINE_MAX_GROWTH; cut to the box), then two go inside the bracket around the best:
    the best of every point run is taken if it lowers f0 by at least LINE_GAIN.

    Returns {"slope": g, "direction": dz, "points": [{"z", "loss"}, ...] in the order run,
    "z": the point taken (z0 when none lowers the loss enough), "loss", "moved"}."""
    points: list[dict] = []
    box = box or {}

    def run(z: dict[str, float]) -> float:
        for point in points:  # in one variable the first point along the line is the probe
            if all(abs(point["z"][n] - z[n]) < 1e-12 for n in z):
                return point["loss"]
        value = float(loss(z))
        value = value if math.isfinite(value) else math.inf
        points.append({"z": dict(z), "loss": value})
        return value

    record = {"slope": None, "direction": None, "points": points, "z": dict(z0), "loss": f0, "moved": False}
    slope = []
    for i, n in enumerate(variables):
        h = LINE_STEP * (-1.0 if g_lm is not None and float(g_lm[i]) > 0 else 1.0)
        if n in box and not box[n][0] <= z0[n] + h <= box[n][1]:
            h = -h
        f1 = run({**z0, n: z0[n] + h})
        slope.append((f1 - f0) / (2 * h))
    g = torch.tensor(slope, dtype=A.dtype)
    record["slope"] = [float(v) for v in g]
    if not bool(torch.isfinite(g).all()) or not bool(g.abs().max() > 0):
        return record
    diagonal = torch.diag(torch.diag(A).clamp(min=1e-12 * float(torch.diag(A).max().clamp(min=1e-30))))
    d = step_of(A + damping * diagonal, g, z0)
    length = float(d.norm())
    if not math.isfinite(length) or length == 0.0:
        return record
    if length > max_step:
        d, length = d * (max_step / length), max_step
    record["direction"] = [float(v) for v in d]

    def at(t: float) -> dict[str, float]:
        z = {**z0, **{n: z0[n] + t * float(d[i]) for i, n in enumerate(variables)}}
        return {n: min(max(v, box[n][0]), box[n][1]) if n in box else v for n, v in z.items()}

    line = [(0.0, f0)]  # (t, loss) in the order of t
    # the first point no nearer than the differences' width: nearer, the estimator's noise
    # swamps the loss's change (and J^T J, which holds the error fixed, sees more curvature
    # than the own-calibration loss has: the trophy's step was a third of LINE_STEP)
    t = min(max(1.0, LINE_STEP / length), max_step / length)
    for _ in range(LINE_MAX_GROWTH):
        f = run(at(t))
        line.append((t, f))
        if f >= line[-2][1] or t * length >= max_step * (1 - 1e-9):
            break
        t = min(t * LINE_GROWTH, max_step / length)
    best = min(range(len(line)), key=lambda k: line[k][1])
    if best == 0:  # the first point is already worse: the bracket is [0, t1]
        inside = [line[1][0] / 3, 2 * line[1][0] / 3]
    elif best == len(line) - 1:  # still falling at the longest step: inside its last interval
        lo, hi = line[best - 1][0], line[best][0]
        inside = [lo + (hi - lo) / 3, lo + 2 * (hi - lo) / 3]
    else:
        inside = [(line[best - 1][0] + line[best][0]) / 2, (line[best][0] + line[best + 1][0]) / 2]
    for t in inside:
        run(at(t))
    lowest = min(points, key=lambda p: p["loss"])
    if lowest["loss"] <= f0 * (1 - LINE_GAIN):
        record.update(z=dict(lowest["z"]), loss=lowest["loss"], moved=True)
    return record


class Steps:
    """One step from a point of an :class:`~clflow.pipeline.fit.objective.Objective`:
    Levenberg-Marquardt in a trust region (More), cut to the local phase's box, or Adam;
    and the line search of the own-calibration loss after Levenberg-Marquardt."""

    def __init__(self, objective: Objective):
        self.objective = objective
        self.problem = objective.problem

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
            before = state.calibrated_at, list(self.objective.errors)
            state = self.objective.calibrate(state, base, frames)
            base = self.objective.rescored(base)
            if comparable and base.loss > best["loss"]:
                # downhill only against the best point's calibration; against its own (each
                # point's loss against the estimator's error on its own simulation, as the
                # search scores) it is worse: the step chased the estimator's error, reject it
                log.info(
                    "step to %s rejected: loss %.4g against the estimator's error there, %.4g at the best point",
                    self.problem.values(state.z),
                    base.loss,
                    best["loss"],
                )
                self.objective.restore_estimator_errors(*before)
                return reject(calibrated_at=before[0])
        best = {"z": dict(state.z), "loss": base.loss, "frames": frames, "substeps": base.substeps}
        r = self.objective.residuals(base.flows, base.more_flows)
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

    def own_loss_line_search(self, state: OptimizerState) -> OptimizerState:
        """After Levenberg-Marquardt stopped at its best point: :func:`line_search` of the
        own-calibration loss (each point's loss against the estimator's error measured on its
        own simulation, as the search and the step rejection score), that error now the mean
        over the camera's JITTER_SHIFTS (smooth where one estimate jumps), along the lightly
        damped (LM_DAMPING) Gauss-Newton direction of LM's Jacobian there.

        LM's Jacobian holds the error fixed: calibrated at C the model's minimum can lie at C
        itself for a range of C (the trophy: every C from 38.5 to 39.5 deg) while the
        own-calibration loss still falls (docs/pipeline.md, "The sand fix, tried and
        reverted"). The search moves only the variables the video pins down there (not weakly
        constrained by the Gauss-Newton test of the identifiability check): along a direction
        the loss barely sees, the smoother error would move a variable by its own noise (the
        toothpaste's shear modulus went 5x from its truth, flat from 2.55e3 to 1e5 Pa). It
        searches again from each point it moves to (LINE_ROUNDS in all). The state moves to
        the lowest point run or stays, either way calibrated with the shift-mean error and
        scored against it (``best``); ``line_search`` records what it did."""
        from clflow.pipeline.fit.diagnostics import gauss_newton_spread
        from clflow.pipeline.fit.objective import JITTER_SHIFTS

        best, frames, variables, grid = (
            state.best,
            self.problem.frames,
            self.problem.main_variables,
            self.problem.model_grid,
        )
        base, J = self.objective.jacobian(best["z"], frames, best.get("substeps", state.substeps), variables, grid)
        state = dataclasses.replace(state, z=dict(best["z"]), substeps=base.substeps)
        state = self.objective.calibrate(state, base, frames, JITTER_SHIFTS)
        base = self.objective.rescored(base)
        f0 = base.loss
        r = self.objective.residuals(base.flows, base.more_flows)
        weak = gauss_newton_spread(J, r).weak(variables)
        moving = tuple(n for n in variables if n not in weak)
        columns = [variables.index(n) for n in moving]
        record = {"from": self.problem.values(best["z"]), "loss_from": f0, "held": weak, "moved": False}
        best = {"z": dict(best["z"]), "loss": f0, "frames": frames, "substeps": base.substeps}
        if not moving:
            log.info("line search of the own-calibration loss: none of %s is pinned down, all stay", list(weak))
            return dataclasses.replace(state, best=best, line_search=record)
        kept: dict = {}  # the lowest point so far: its loss, evaluation and estimator's error

        def own_loss(z: dict[str, float]) -> float:
            try:
                result = self.objective.evaluate(z, frames, with_grad=False, grid=grid)
                errors = self.objective.estimator_errors(result, frames, JITTER_SHIFTS)
            except (FloatingPointError, ClflowError) as exc:
                log.info("line search: %s fails (%s)", self.problem.values(z), exc)
                return math.inf
            loss = float(self.objective.loss_of([result.flows, *result.more_flows], errors))
            if loss < kept.get("loss", math.inf):
                kept.update(loss=loss, z=dict(z), result=result, errors=errors)
            return loss

        Jm = J[:, columns]
        z, loss, slope, rounds = dict(best["z"]), f0, Jm.T @ r, []
        for _ in range(LINE_ROUNDS):
            found = line_search(
                own_loss,
                z,
                loss,
                Jm.T @ Jm,
                LM_DAMPING,
                moving,
                lambda M, g, at: self.bounded_step(M, g, at, moving),
                g_lm=slope,  # the first probe on the downhill side of LM's J^T r, then of the last slope
                box=self.problem.local_box(),
            )
            rounds.append(
                {
                    "slope": found["slope"],
                    "direction": found["direction"],
                    "points": [{"params": self.problem.values(p["z"]), "loss": p["loss"]} for p in found["points"]],
                    "moved": found["moved"],
                }
            )
            if not found["moved"]:
                break
            z, loss, slope = found["z"], found["loss"], torch.tensor(found["slope"], dtype=J.dtype)
        moved = loss < f0  # then the lowest point run is the state's (a last round's may lie a little lower)
        if moved:
            z, loss = kept["z"], kept["loss"]
        record.update(rounds=rounds, moved=moved, to=self.problem.values(z), loss=loss)
        points = sum(len(each["points"]) for each in rounds)
        held = f", {list(weak)} held" if weak else ""
        if not moved:
            lowest = min([p["loss"] for each in rounds for p in each["points"]], default=math.inf)
            log.info(
                "line search of the own-calibration loss from %s (loss %.4g%s): stays; its %d points "
                "lower it by %.2g %% at most (under %g %%)",
                record["from"],
                f0,
                held,
                points,
                max(0.0, 100 * (1 - lowest / f0)),
                100 * LINE_GAIN,
            )
            return dataclasses.replace(state, best=best, line_search=record)
        log.info(
            "line search of the own-calibration loss from %s (loss %.4g%s): to %s, loss %.4g (%.2g %% lower; "
            "%d round(s), %d points)",
            record["from"],
            f0,
            held,
            record["to"],
            loss,
            100 * (1 - loss / f0),
            len(rounds),
            points,
        )
        result = kept["result"]
        moved_state = dataclasses.replace(state, z=dict(kept["z"]), substeps=result.substeps, line_search=record)
        moved_state = self.objective.calibrate(moved_state, result, frames, JITTER_SHIFTS, errors=kept["errors"])
        best = {"z": dict(kept["z"]), "loss": kept["loss"], "frames": frames, "substeps": result.substeps}
        return dataclasses.replace(moved_state, best=best)

    def bounded_step(
        self, M: torch.Tensor, g: torch.Tensor, z: dict[str, float], variables: tuple[str, ...]
    ) -> torch.Tensor:
        """The step [P] solving M step = -g, with a variable that sits on its box edge while the
        step would push it out held there and the rest solved again without it (the clipped
        step would otherwise promise what it cannot deliver, and rejected steps repeat)."""
        box = self.problem.local_box()
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
        _, iteration, iterations = phase_of(self.problem.cfg.optimize, state.iteration)
        k = iteration + 1  # gradients in v since the phase began (for Adam's bias correction)
        schedule = rate_schedule(self.problem.cfg.optimize, iteration, iterations)
        for n, g in grads.items():
            g *= scale
            m[n] = BETAS[0] * m[n] + (1 - BETAS[0]) * g
            v[n] = BETAS[1] * v[n] + (1 - BETAS[1]) * g * g
            m_hat, v_hat = m[n] / (1 - BETAS[0] ** k_m), v[n] / (1 - BETAS[1] ** k)
            rate = learning_rate(self.problem.cfg, n) * state.step_scale * schedule
            z[n] -= rate * m_hat / (math.sqrt(v_hat) + ADAM_EPS)
        return dataclasses.replace(
            state, iteration=state.iteration + 1, z=z, m=m, v=v, history=list(state.history), momentum_steps=k_m
        )
