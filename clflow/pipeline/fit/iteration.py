"""One iteration of an optimisation: evaluate the point, step from it, and what a failure,
a convergence or the end of a phase does to the state."""

from __future__ import annotations

import dataclasses
import logging
import time

import torch

from clflow.errors import ClflowError
from clflow.pipeline.fit.state import LM_DAMPING, Evaluation, OptimizerState
from clflow.pipeline.fit.steps import LM_GAIN_TOLERANCE, LM_TOLERANCE, Steps, horizon, phase_of

log = logging.getLogger(__name__)

MAX_FAILURES = 4  # consecutive failed iterations before giving up


class Iterations:
    """The iterations of an optimisation with :class:`~clflow.pipeline.fit.steps.Steps`
    (and their objective and problem): :meth:`step` runs one from a state to the next."""

    def __init__(self, steps: Steps):
        self.steps = steps
        self.objective = steps.objective
        self.problem = steps.problem

    def step(
        self, state: OptimizerState, failures: int, start: int | None = None
    ) -> tuple[OptimizerState, int, dict | None]:
        """One iteration from ``state`` (``start``: of that start's polish), ``failures`` the
        consecutive failed ones before it. Returns the new state, the failures, and the
        iteration's history row (None when it failed and was rolled back)."""
        opt = self.problem.cfg.optimize
        lm = opt.method == "levenberg_marquardt"
        phase, iteration, _ = phase_of(opt, state.iteration)
        if phase == "velocity":
            frames, variables = opt.estimate_velocity_frames, self.problem.velocity_variables
        else:
            frames, variables = horizon(self.problem.cfg, iteration), self.problem.main_variables
        grid = (
            self.problem.model_grid if start is None else self.problem.search_grid
        )  # a start's polish: the global phase's
        began = time.perf_counter()
        J = None
        try:
            if lm:
                result, J = self.objective.jacobian(state.z, frames, state.substeps, variables, grid)
            else:
                result = self.objective.evaluate(
                    state.z, frames, min_substeps=state.substeps, variables=variables, grid=grid
                )
        except (FloatingPointError, ClflowError) as exc:
            return self.rolled_back(state, failures + 1, phase, start, exc), failures + 1, None
        row = {
            "iteration": state.iteration,
            "phase": phase,
            "loss": result.loss,
            "frames": frames,
            "z": dict(state.z),
            "params": self.problem.values(state.z),
            "substeps": result.substeps,
            "grid": grid,
            "seconds": time.perf_counter() - began,
        }
        moved = self.moved(state, result, J, frames, variables, phase)
        if moved.calibrated_at is not state.calibrated_at:
            row["calibrated"] = True
        if lm and state.best is not None and moved.best is state.best and state.z != state.best["z"]:
            row["rejected"] = True  # the trial's loss, lower or not, did not beat the best point's
        return self.iteration_done(moved, state, row, variables, phase, start), 0, row

    def rolled_back(
        self, state: OptimizerState, failures: int, phase: str, start: int | None, exc: Exception
    ) -> OptimizerState:
        """``state`` after its iteration failed (``exc``, the ``failures``-th in a row): back
        at the last good parameters with half the step, no momentum and more damping; raises
        ClflowError after MAX_FAILURES (or a failing first point)."""
        # a start's polish goes back within its own rows only (else to its start point)
        own = [r for r in state.history if start is None or r.get("start") == start]
        if failures > MAX_FAILURES or state.iteration == 0 and start is None and failures > 1:
            good = (
                f"last good parameters: {self.problem.values(own[-1]['z'])}"
                if own
                else f"the initial parameters {self.problem.values(state.z)} fail"
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
            "params": self.problem.values(state.z),
            "back_to": self.problem.values(previous),
        }
        return dataclasses.replace(
            state,
            z=dict(previous),
            m={n: 0.0 for n in state.m},
            step_scale=state.step_scale / 2,
            momentum_steps=0,
            damping=state.damping * 4.0,
            rollbacks=[*state.rollbacks, rollback],
        )

    def moved(
        self,
        state: OptimizerState,
        result: Evaluation,
        J: torch.Tensor | None,
        frames: int,
        variables: tuple[str, ...],
        phase: str,
    ) -> OptimizerState:
        """``state`` after one step from ``result`` (a Levenberg-Marquardt step with the
        Jacobian ``J``, else Adam), calibrated where the bias correction asks, kept in the
        search's box and with the substeps the next run starts from."""
        lm = J is not None
        calibrate = self.problem.corrects_bias and phase == "main"
        if lm:
            state = self.steps.lm_step(state, result, J, frames, variables, calibrate=calibrate)
        else:
            if calibrate:  # the next iteration fits the error measured here
                state = self.objective.calibrate(state, result, frames)
            state = self.steps.adam_step(state, result.grads)
        if phase == "main":  # the local phase stays in the search's box
            box = self.problem.local_box()
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
        return state

    @staticmethod
    def stop_reason(state: OptimizerState, previous: OptimizerState, variables: tuple[str, ...]) -> str | None:
        """Why Levenberg-Marquardt stops after moving ``previous`` to ``state``, or None."""
        if state.converged:
            return f"converged: the model promises a fall of under {LM_GAIN_TOLERANCE:g} of the loss"
        if state.best is not None and state.best is not previous.best:
            if max(abs(state.z[n] - state.best["z"][n]) for n in variables) < LM_TOLERANCE:
                return f"converged: the next step moves every variable by under {LM_TOLERANCE:g} (optimiser units)"
        return None

    def iteration_done(
        self,
        state: OptimizerState,
        previous: OptimizerState,
        row: dict,
        variables: tuple[str, ...],
        phase: str,
        start: int | None,
    ) -> OptimizerState:
        """``state`` (moved from ``previous``) with ``row`` in its history, marked done when
        the iteration converged (a start's polish: or ran its iterations), and with fresh
        moments, step scale and damping when the next iteration is in another phase."""
        opt = self.problem.cfg.optimize
        lm = opt.method == "levenberg_marquardt"
        stop = self.stop_reason(state, previous, variables) if lm and phase == "main" else None
        if start is not None:  # a start's polish ends after its iterations or when it converges
            row["start"] = start
            done = 1 + sum(1 for r in state.history if r.get("start") == start)
            if stop or done >= opt.search.start_iterations:
                row["start_done"] = True
                reason = stop or f"ran its {opt.search.start_iterations} iteration(s)"
                log.info("start %d stopped after %d iteration(s): %s", start + 1, done, reason)
        elif stop:
            row["converged"] = True  # the step would change nothing that matters: stop here
            log.info("stopped after iteration %d of %d: %s", state.iteration, self.problem.total_iterations, stop)
            state = dataclasses.replace(state, iteration=self.problem.total_iterations)
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
        return state
