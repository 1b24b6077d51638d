"""The optimisation run: its setup, the loop over iterations and one iteration (step),
from the parts in the other modules of clflow.pipeline.fit."""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import time
from typing import Callable, Sequence

import torch

from clflow.errors import ClflowError, InputError
from clflow.limits import format_duration
from clflow.pipeline.fit.budget import BudgetTooSmall, GridChoice, choose_grid, load_choice, save_choice
from clflow.pipeline.fit.diagnostics import Diagnostics
from clflow.pipeline.fit.guidance import guidance_views_of
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.results import Results
from clflow.pipeline.fit.search import Search
from clflow.pipeline.fit.starts import quiet, serial_starts
from clflow.pipeline.fit.state import LM_DAMPING, Checkpoints, Evaluation, OptimizerState, config_digests
from clflow.pipeline.fit.steps import LM_GAIN_TOLERANCE, LM_TOLERANCE, Steps, horizon, phase_of
from clflow.pipeline.forward import prepare
from clflow.pipeline.generated_video import ensure_guidance_video
from clflow.pipeline.material import resolve_material
from clflow.scene.config import (
    VELOCITY,
    SceneConfig,
    main_grid_range,
    split_parameter,
    velocity_names,
)

log = logging.getLogger(__name__)

MAX_FAILURES = 4  # consecutive failed iterations before giving up


def _parameterizations(cfg: SceneConfig):
    """Material parameter name -> its parameterisation, for each of optimize.parameters
    but a velocity (with several objects OBJECT.PARAM, of that object's material)."""
    from clflow.mpm.parameterization import parameterization

    names = cfg.optimize.parameters
    if not names:
        raise InputError(f"{cfg.source}: optimize.parameters is empty: name the parameters to optimise")
    out = {}
    for name in names:
        k, param = split_parameter(cfg.objects, name)
        if param != VELOCITY:
            out[name] = parameterization(cfg.objects[k].material.type, param)
    return out


class Optimization(Checkpoints, Objective, Steps, Search, Diagnostics, Results):
    """One optimisation run of a config (see the module docstring); its parts are the mixins
    of clflow.pipeline.fit (state, objective, steps, search, diagnostics, results)."""

    def __init__(
        self,
        cfg: SceneConfig,
        *,
        progress: Callable[[dict], None] | None = None,
        hypotheses: dict | None = None,
        force_video: bool = False,
    ):
        self.started = time.perf_counter()
        self.cfg = cfg = ensure_guidance_video(resolve_material(cfg))  # video: {generate: ...} made first
        self.hypotheses = hypotheses  # how the material was chosen (clflow.pipeline.hypotheses), for metrics
        self.params = _parameterizations(cfg)
        opt = cfg.optimize
        # each object's velocity components where optimize.parameters names its velocity; the
        # velocity phase's: the one object's, or those of estimate_velocity.objects
        velocities = [velocity_names(cfg.objects, k) for k in range(len(cfg.objects))]
        optimised = tuple(c for name, components in velocities if name in opt.parameters for c in components)
        self.velocity_variables = tuple(
            c
            for o, (_, components) in zip(cfg.objects, velocities)
            if opt.estimate_velocity_iterations and (len(cfg.objects) == 1 or o.name in opt.estimate_velocity_objects)
            for c in components
        )
        estimated = tuple(c for c in self.velocity_variables if c not in optimised)
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
        # optimize.budget: seconds after ``started`` by which the search must end (check_budget)
        self.search_deadline: float | None = None
        self.grid_choice = self.check_budget() if opt.budget is not None else None
        self.preflight()  # before the optical flow: refuse a run beyond the substep limit in seconds
        self.views = guidance_views_of(cfg, self.prepared, self.frames)
        self.guidance_warnings = self.check_guidance(force_video)
        self.checkpoint = cfg.output / "checkpoint.json"
        self.estimator_error_file = cfg.output / "estimator_error.npz"  # a start's polish: its own
        # polishes every search start (records of Optimization.polish, in start order): one after
        # another here, or as Ray tasks (starts_on_ray: optimize --parallel)
        self.map_starts: Callable[..., list[dict]] = serial_starts
        # (z, frames, variables, substeps) -> (Evaluation, J) of the last two Jacobians: the best
        # point's and the last step's, so that a rejected step goes back without new runs
        self._lm_cache: dict[tuple, tuple[Evaluation, torch.Tensor]] = {}

    def budget_key(self) -> dict:
        """What a saved grid choice must match: the device and the config (budget.json)."""
        from clflow.environment import environment

        return {"device": environment()["device"], "config": config_digests(self.cfg)}

    def check_budget(self) -> GridChoice | None:
        """Before any work: the choice made before for this config and device (a resumed run
        goes on on its grid), else None once the whole run on the coarsest grid (the search's
        samples at their own substeps, the rest at the start's) is predicted to fit
        ``optimize.budget`` (InputError if not); the search is then to end by the budget less
        the rest's predicted seconds (``search_deadline``)."""
        choice = load_choice(self.cfg.output / "budget.json", self.budget_key())
        if choice is not None:
            self.move_to_grid(choice)
            return choice
        lowest = main_grid_range(self.cfg.optimize, self.cfg.simulation)[0]
        z0 = self.initial_state().z
        # each search sample's substeps; one beyond simulation.max_substeps is refused unrun
        design = (
            [self.rest_substeps(self.search_grid, z) for z in self.search_points(z0)]
            if self.cfg.optimize.search
            else []
        )
        design = [n for n in design if n <= self.cfg.simulation.max_substeps]
        coarsest = self.grid_options((lowest, lowest), z0, self.cfg.optimize.budget.seconds, design_substeps=design)
        if coarsest.predicted_seconds > coarsest.budget_seconds:
            raise BudgetTooSmall(coarsest.too_small())
        self.search_deadline = coarsest.budget_seconds - coarsest.rest_seconds
        log.info(
            "budget: the whole run on the coarsest main grid (%d nodes) is predicted to take %s of %s",
            coarsest.grid,
            format_duration(coarsest.predicted_seconds),
            format_duration(coarsest.budget_seconds),
        )
        return None

    def choose_main_grid(self, state: OptimizerState) -> GridChoice:
        """When the main phase begins at state.z: the finest main grid whose remaining work
        fits what is left of ``optimize.budget`` (the coarsest, with a warning, when none does),
        the search's starts' polishes each costed at the substeps its parameters ask; saved in
        output/budget.json, and the run moves to it."""
        spent = time.perf_counter() - self.started
        grids = main_grid_range(self.cfg.optimize, self.cfg.simulation)
        key = self.budget_key()
        polish = [self.rest_substeps(self.search_grid, z) for z in state.starts]
        left = self.cfg.optimize.budget.seconds - spent
        choice = self.grid_options(grids, state.z, left, searched=True, polish_substeps=polish)
        choice = dataclasses.replace(choice, spent_seconds=spent)
        save_choice(self.cfg.output / "budget.json", key, choice)
        self.move_to_grid(choice)
        return choice

    def grid_options(
        self,
        grids: tuple[int, int],
        z: dict[str, float],
        budget: float,
        searched: bool = False,
        design_substeps: Sequence[int] = (),
        polish_substeps: Sequence[int] = (),
    ) -> GridChoice:
        """clflow.pipeline.fit.budget.choose_grid at z: candidates timed there, the substeps of
        z's motion from its run on the search grid."""
        moving = (self.search_grid, self.start_substeps(self.search_grid, z))
        plan_on = functools.partial(self.plan_on, z=z)
        variables = len(self.main_variables)
        return choose_grid(
            self.cfg.optimize,
            grids,
            self.frames,
            variables,
            moving,
            plan_on,
            budget,
            searched=searched,
            design_substeps=design_substeps,
            polish_substeps=polish_substeps,
        )

    def move_to_grid(self, choice: GridChoice) -> None:
        """The main phase's grid, config and prepared scene become ``choice``'s (logged; a
        warning when even the coarsest overruns what is left of the budget)."""
        if choice.predicted_seconds > choice.budget_seconds:
            log.warning("%s: the budget is overrun, the main phase runs on the coarsest grid", choice.describe())
        else:
            log.info("%s", choice.describe())
        self.model_grid = choice.grid
        self.prepared = self.prepared_on(choice.grid)
        self.cfg = self.prepared.cfg
        self._prepared = {g: p for g, p in self._prepared.items() if g in (self.search_grid, self.model_grid)}

    def task_copy(self) -> Optimization:
        """This run as a Ray task gets it (clflow.pipeline.fit.starts.starts_on_ray): no
        progress callback (the rows are shown where the task's record arrives), its starts
        polished in place, no cached Jacobians."""
        task = copy.copy(self)
        task.progress, task.map_starts, task._lm_cache = quiet, serial_starts, {}
        return task

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
            if phase_of(opt, state.iteration)[0] == "main" and opt.budget is not None and self.grid_choice is None:
                self.grid_choice = self.choose_main_grid(state)
            if len(state.polished) < len(state.starts):
                most = None if stop_after is None else stop_after - done_here
                polish_all = self.map_starts if most is None else serial_starts  # stop_after: tests, here
                records = polish_all(self, state, range(len(state.starts)), resume, most)
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
        last = state.history[-1] if state.history else {}
        if state.iteration >= self.total_iterations and not last.get("converged") and done_here:
            log.info("stopped: ran its %d iteration(s)", self.total_iterations)
        best = state.best
        if (
            opt.method == "levenberg_marquardt"
            and best is not None
            and state.iteration >= self.total_iterations
            and state.z != best["z"]
        ):  # the last step was never run: the result is the best point found
            state = dataclasses.replace(state, z=dict(best["z"]), substeps=best.get("substeps", state.substeps))
            self.save_state(state)
        if (
            opt.method == "levenberg_marquardt"
            and self.corrects_bias
            and best is not None
            and best["frames"] == self.frames
            and state.iteration >= self.total_iterations
            and state.line_search is None
        ):  # LM stopped where its Jacobian, which holds the estimator's error fixed, sees no progress
            state = self.own_loss_line_search(state)
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
            frames, variables = opt.estimate_velocity_frames, self.velocity_variables
        else:
            frames, variables = horizon(self.cfg, iteration), self.main_variables
        grid = self.model_grid if start is None else self.search_grid  # a start's polish: the global phase's
        began = time.perf_counter()
        J = None
        try:
            if lm:
                result, J = self.jacobian(state.z, frames, state.substeps, variables, grid)
            else:
                result = self.evaluate(state.z, frames, min_substeps=state.substeps, variables=variables, grid=grid)
        except (FloatingPointError, ClflowError) as exc:
            return self.rolled_back(state, failures + 1, phase, start, exc), failures + 1, None
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
        calibrate = self.corrects_bias and phase == "main"
        if lm:
            state = self.lm_step(state, result, J, frames, variables, calibrate=calibrate)
        else:
            if calibrate:  # the next iteration fits the error measured here
                state = self.calibrate(state, result, frames)
            state = self.adam_step(state, result.grads)
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
        opt = self.cfg.optimize
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
            log.info("stopped after iteration %d of %d: %s", state.iteration, self.total_iterations, stop)
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
        return state
