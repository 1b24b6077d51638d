"""The optimisation run: its parts put together, the budget's choice of grid, and the loop
over the phases and iterations, checkpointed after each."""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from pathlib import Path
from typing import Callable, Sequence

from clflow.errors import ClflowError
from clflow.limits import format_duration
from clflow.pipeline.fit.budget import BudgetTooSmall, GridChoice, choose_grid, load_choice, save_choice
from clflow.pipeline.fit.checkpoint import Checkpoint
from clflow.pipeline.fit.diagnostics import Diagnostics
from clflow.pipeline.fit.guidance import guidance_views_of
from clflow.pipeline.fit.iteration import Iterations
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.problem import Problem
from clflow.pipeline.fit.results import Results
from clflow.pipeline.fit.search import Search, SearchDesign, StartPolish, StartsMapper, quiet, serial_starts
from clflow.pipeline.fit.state import OptimizerState, config_digests
from clflow.pipeline.fit.steps import Steps, phase_of
from clflow.pipeline.generated_video import ensure_guidance_video
from clflow.pipeline.material import resolve_material
from clflow.scene.config import SceneConfig, is_velocity_component, main_grid_range

log = logging.getLogger(__name__)


class Optimization:
    """One optimisation run of a config (see the package docstring).

    Its parts, each an object of its own: ``problem`` (what is fitted), ``objective`` (the
    loss and the flow estimator's calibration), ``steps`` and ``iterations`` (one step, one
    iteration), ``search`` and ``polish`` (the global phase and its starts' polishes),
    ``diagnostics`` (identifiability and the grid check) and ``checkpoint``. ``progress``
    gets each iteration's and search sample's row; ``map_starts`` maps the starts' polishes
    (clflow.pipeline.fit.search: serially, or as Ray tasks)."""

    def __init__(
        self,
        cfg: SceneConfig,
        *,
        progress: Callable[[dict], None] | None = None,
        hypotheses: dict | None = None,
        force_video: bool = False,
    ):
        self.started = time.perf_counter()
        cfg = ensure_guidance_video(resolve_material(cfg))  # video: {generate: ...} made first
        self.hypotheses = hypotheses  # how the material was chosen (clflow.pipeline.hypotheses), for metrics
        self.progress = progress or quiet
        self.map_starts: StartsMapper = serial_starts
        self.problem = problem = Problem(cfg)
        # optimize.budget: seconds after ``started`` by which the search must end (check_budget)
        search_deadline: float | None = None
        self.grid_choice: GridChoice | None = None
        if cfg.optimize.budget is not None:
            self.grid_choice, search_deadline = self.check_budget()
        problem.preflight()  # before the optical flow: refuse a run beyond the substep limit in seconds
        problem.views = guidance_views_of(problem.cfg, problem.prepared, problem.frames)
        self.objective = Objective(problem, cfg.output / "estimator_error.npz")
        self.steps = Steps(self.objective)
        self.iterations = Iterations(self.steps)
        self.diagnostics = Diagnostics(self.objective)
        self.checkpoint = Checkpoint(cfg.output / "checkpoint.json", problem)
        self.search = Search(self.objective, self.checkpoint, self.started, search_deadline)
        self.polish = StartPolish(self.objective)
        self.guidance: list = []
        self.guidance_warnings = self.check_guidance(force_video)

    @property
    def cfg(self) -> SceneConfig:
        """The config the main phase runs (its grid the budget's choice)."""
        return self.problem.cfg

    def budget_key(self) -> dict:
        """What a saved grid choice must match: the device and the config (budget.json)."""
        from clflow.environment import environment

        return {"device": environment()["device"], "config": config_digests(self.cfg)}

    def check_budget(self) -> tuple[GridChoice | None, float | None]:
        """Before any work: the choice made before for this config and device (a resumed run
        goes on on its grid), else none once the whole run on the coarsest grid (the search's
        samples at their own substeps, the rest at the start's) is predicted to fit
        ``optimize.budget`` (InputError if not); returns the choice and the seconds by which
        the search is then to end: the budget less the rest's predicted seconds."""
        problem = self.problem
        choice = load_choice(self.cfg.output / "budget.json", self.budget_key())
        if choice is not None:
            self.move_to_grid(choice)
            return choice, None
        lowest = main_grid_range(self.cfg.optimize, self.cfg.simulation)[0]
        z0 = problem.initial_state().z
        # each search sample's substeps; one beyond simulation.max_substeps is refused unrun
        design = (
            [problem.rest_substeps(problem.search_grid, z) for z in SearchDesign(problem).search_points(z0)]
            if self.cfg.optimize.search
            else []
        )
        design = [n for n in design if n <= self.cfg.simulation.max_substeps]
        coarsest = self.grid_options((lowest, lowest), z0, self.cfg.optimize.budget.seconds, design_substeps=design)
        if coarsest.predicted_seconds > coarsest.budget_seconds:
            raise BudgetTooSmall(coarsest.too_small())
        log.info(
            "budget: the whole run on the coarsest main grid (%d nodes) is predicted to take %s of %s",
            coarsest.grid,
            format_duration(coarsest.predicted_seconds),
            format_duration(coarsest.budget_seconds),
        )
        return None, coarsest.budget_seconds - coarsest.rest_seconds

    def choose_main_grid(self, state: OptimizerState) -> GridChoice:
        """When the main phase begins at state.z: the finest main grid whose remaining work
        fits what is left of ``optimize.budget`` (the coarsest, with a warning, when none does),
        the search's starts' polishes each costed at the substeps its parameters ask; saved in
        output/budget.json, and the run moves to it."""
        spent = time.perf_counter() - self.started
        grids = main_grid_range(self.cfg.optimize, self.cfg.simulation)
        key = self.budget_key()
        polish = [self.problem.rest_substeps(self.problem.search_grid, z) for z in state.starts]
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
        problem = self.problem
        moving = (problem.search_grid, problem.start_substeps(problem.search_grid, z))
        plan_on = functools.partial(problem.plan_on, z=z)
        return choose_grid(
            self.cfg.optimize,
            grids,
            problem.frames,
            len(problem.main_variables),
            moving,
            plan_on,
            budget,
            searched=searched,
            design_substeps=design_substeps,
            polish_substeps=polish_substeps,
        )

    def move_to_grid(self, choice: GridChoice) -> None:
        """The main phase's grid becomes ``choice``'s (logged; a warning when even the
        coarsest overruns what is left of the budget)."""
        if choice.predicted_seconds > choice.budget_seconds:
            log.warning("%s: the budget is overrun, the main phase runs on the coarsest grid", choice.describe())
        else:
            log.info("%s", choice.describe())
        self.problem.move_to_grid(choice.grid)

    def check_guidance(self, force: bool) -> list[str]:
        """The guidance checks of every view (clflow.pipeline.preflight.check_guidance), kept
        in ``guidance``: their problems when forced, else InputError on any."""
        from clflow.pipeline.preflight import AGREEMENT_FRAMES, check_guidance, flow_agreement, measure_view

        problem = self.problem
        # inside the mask the weight is the observed flow's confidence
        self.guidance = [
            measure_view(
                problem.prepared, view.camera, view.mask, view.video_frames, view.observed.numpy(), view.weight.numpy()
            )
            for view in problem.views
        ]
        if not any(map(is_velocity_component, problem.variables)):  # else the start's velocity may be anything
            frames = min(AGREEMENT_FRAMES, problem.frames)
            try:
                start = self.objective.evaluate(problem.initial_state().z, frames, with_grad=False)
            except (FloatingPointError, ClflowError) as exc:  # the first iteration will say so
                log.info("no flow-direction check: the start's simulation fails (%s)", exc)
            else:
                self.guidance = [
                    dataclasses.replace(check, agreement=flow_agreement(flows, view.observed, view.weight))
                    for check, view, flows in zip(self.guidance, problem.views, [start.flows, *start.more_flows])
                ]
        return check_guidance(self.cfg, self.guidance, force)

    def load_state(self) -> OptimizerState:
        """The checkpoint's state, the objective's calibration restored as it was then."""
        state = self.checkpoint.load()
        if state.calibrated_at is not None:
            self.objective.restore_calibration(state)
        return state

    def run(
        self, resume: bool = False, stop_after: int | None = None, start: OptimizerState | None = None
    ) -> OptimizerState:
        """Optimise for the velocity phase's and ``optimize.iterations`` iterations
        (``stop_after``: at most this many in this call, for tests of resuming), from the
        checkpoint (``resume``), else ``start``, else the initial state; returns the final
        state. Each phase starts with fresh Adam moments and step scale. The starts'
        polishes (``optimize.search.starts``) run through ``self.map_starts``."""
        opt, total = self.cfg.optimize, self.problem.total_iterations
        self.cfg.output.mkdir(parents=True, exist_ok=True)
        if resume and self.checkpoint.exists():
            state = self.load_state()
        else:
            state = start or self.problem.initial_state()
        failures, done_here = 0, 0
        while state.iteration < total and (stop_after is None or done_here < stop_after):
            if phase_of(opt, state.iteration)[0] == "main" and opt.search is not None and not state.searched:
                state = self.search.global_search(state, self.progress)  # after the velocity phase: from its estimate
            if phase_of(opt, state.iteration)[0] == "main" and opt.budget is not None and self.grid_choice is None:
                self.grid_choice = self.choose_main_grid(state)
            if len(state.polished) < len(state.starts):
                starts = range(len(state.starts))
                if stop_after is None:
                    records = self.map_starts(self.polish, state, starts, resume, self.progress)
                else:  # tests of resuming: here, at most the iterations left
                    most = stop_after - done_here
                    records = serial_starts(self.polish, state, starts, resume, self.progress, max_iterations=most)
                done_here += sum(r["iterations_here"] for r in records)
                if not all(r["finished"] for r in records):  # stopped by stop_after
                    return state
                state = self.search.keep_best_start(state, records)
                self.checkpoint.save(state)
                continue
            state, failures, row = self.iterations.step(state, failures)
            if row is not None:
                self.checkpoint.save(state)
                self.progress(row)
                done_here += 1
        last = state.history[-1] if state.history else {}
        if state.iteration >= total and not last.get("converged") and done_here:
            log.info("stopped: ran its %d iteration(s)", total)
        best = state.best
        if (
            opt.method == "levenberg_marquardt"
            and best is not None
            and state.iteration >= total
            and state.z != best["z"]
        ):
            # the last step was never run: the result is the best point found
            state = dataclasses.replace(state, z=dict(best["z"]), substeps=best.get("substeps", state.substeps))
            self.checkpoint.save(state)
        if (
            opt.method == "levenberg_marquardt"
            and self.problem.corrects_bias
            and best is not None
            and best["frames"] == self.problem.frames
            and state.iteration >= total
            and state.line_search is None
        ):  # LM stopped where its Jacobian, which holds the estimator's error fixed, sees no progress
            state = self.steps.own_loss_line_search(state)
            self.checkpoint.save(state)
        return state

    def results(self) -> Results:
        """The writer of this run's results folder: its fields are this run's parts and records
        of the same names."""
        return Results(**{f.name: getattr(self, f.name) for f in dataclasses.fields(Results)})

    def write_result_files(self, state: OptimizerState, out: Path) -> dict:
        """params.json, metrics.json, history.json, loss.png and the comparison videos of the
        final ``state`` in folder ``out`` (clflow.pipeline.runs.write_results's staging
        folder); returns the metrics."""
        return self.results().write_result_files(state, out)
