"""The main grid a time budget affords (``optimize.budget``, ``clflow optimize --budget``).

An optimisation's time is counted in simulations: the search's forward runs and the starts'
polishes on the search grid; the velocity phase, the main iterations (each over its loss
horizon) and the diagnostics on the main grid. A run on a grid costs frames x substeps x the
seconds of one substep (timed on that grid) plus the flow's rendering per frame; a gradient
iteration costs GRADIENT_COST forward runs (Adam), or one run per variable and the point
itself (Levenberg-Marquardt's Jacobian).

Three moments use it. Before any work, the whole run on the coarsest grid (the search's
samples at their own parameters' substeps, the rest at the starting parameters') must fit
the budget, else the run is refused with its prediction. The search ends once it has used
the time that leaves the rest its predicted seconds (GridChoice.rest_seconds). When the main phase begins (after
the search, where the parameters are near their fit and the search's time is spent), the
candidates go from the coarsest grid up, each timed at the current parameters, and the
finest whose remaining work fits the budget left is chosen. Parameters
that stiffen later, or rejected LM steps, take longer than predicted: the prediction's error
is measured in docs/pipeline.md.

The choice is kept in ``output/budget.json`` with the device and the config it was made for:
a rerun of that config on that device (``--resume``, an interrupted sysid case) keeps its
grid instead of timing again.
"""

from __future__ import annotations

import json
import logging
import math
import statistics
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

from clflow.errors import InputError
from clflow.fileio import atomic_write_text
from clflow.fileio.reading import parse_json
from clflow.limits import format_duration
from clflow.pipeline.fit.diagnostics import GRID_CHECK_RATIO
from clflow.pipeline.preflight import GRADIENT_COST, RunPlan
from clflow.pipeline.simulation import SubstepLimitError
from clflow.scene.config import OptimizeSettings

log = logging.getLogger(__name__)


class BudgetTooSmall(InputError):
    """optimize.budget is below the prediction of the whole run on the coarsest grid."""


# the candidates' cells per side as multiples of the coarsest grid's
GRID_SCALES = (1.0, 1.25, 1.5, 1.75, 2.0, 2.5, 3.0, 3.5, 4.0)


@dataclass(frozen=True)
class GridChoice:
    """The main grid (nodes along the domain's longest side) a budget (s) affords, the run's
    predicted seconds on it, and every candidate timed: (nodes, predicted seconds)."""

    grid: int
    predicted_seconds: float  # what is left of the run on ``grid``
    budget_seconds: float  # what was left of the budget
    candidates: tuple[tuple[int, float], ...]
    spent_seconds: float = 0.0  # before the choice: setup, velocity phase, search
    # of predicted_seconds, what comes after the search on ``grid`` (the starts' polishes and
    # their comparison, the main phase, the diagnostics): the search must end by budget - this
    rest_seconds: float = 0.0

    def describe(self) -> str:
        timed = ", ".join(f"{g} nodes {format_duration(s)}" for g, s in self.candidates)
        return (
            f"budget: {format_duration(self.spent_seconds)} spent, {format_duration(self.budget_seconds)} left: "
            f"main grid {self.grid} nodes, predicted {format_duration(self.predicted_seconds)} (timed: {timed})"
        )

    def too_small(self) -> str:
        """The error of a budget below the coarsest candidate's prediction."""
        grid, seconds = self.candidates[0]
        return (
            f"optimize.budget: {format_duration(self.budget_seconds)} is too small: on the coarsest main grid it "
            f"may choose ({grid} nodes) the optimisation is predicted to take {format_duration(seconds)}; raise "
            f"the budget to at least {format_duration(math.ceil(seconds))}, or lower optimize.iterations or the "
            f"search's samples"
        )


def candidate_grids(lowest: int, highest: int) -> list[int]:
    """Grids (nodes) from ``lowest`` to ``highest``, by GRID_SCALES of the coarsest's cells."""
    return sorted({min(highest, round((lowest - 1) * s) + 1) for s in GRID_SCALES})


def run_seconds(plan: RunPlan, frames: int, gradient: bool = False) -> float:
    """Seconds of one run over ``frames`` frames on ``plan``'s grid, the flow rendered each
    frame (``gradient``: with the adjoint)."""
    per_frame = plan.substeps * plan.seconds_per_substep * (GRADIENT_COST if gradient else 1.0)
    return frames * (per_frame + plan.render_seconds_per_frame)


def iteration_seconds(opt: OptimizeSettings, plan: RunPlan, frames: int, variables: int) -> float:
    """One local-phase iteration: Adam's gradient run, or LM's point and Jacobian columns."""
    if opt.method == "levenberg_marquardt":
        return (1 + variables) * run_seconds(plan, frames)
    return run_seconds(plan, frames, gradient=True)


def diagnostic_runs(variables: int) -> int:
    """Forward runs after the last iteration, in runs on the main grid: the Jacobian (1 + P),
    a profile of each weak parameter (2 P at most), the grid checks (one on a coarser grid,
    one on a GRID_CHECK_RATIO times finer grid: its cells and substeps make it
    GRID_CHECK_RATIO^4 runs), the time-step check at twice the substeps (2),
    the walks of the ranges' ends (three runs an end: one where the Gauss-Newton end holds, up
    to six where the loss flattens; 2.6 on average over the 69 ends the paper's nine, the
    extra set and the quick set walked), the final evaluation."""
    return 1 + variables + 2 * variables + 1 + round(GRID_CHECK_RATIO**4) + 2 + 6 * variables + 1


def typical_sample(search: RunPlan, design_substeps: Sequence[int]) -> RunPlan:
    """``search`` at the median of the design's substeps per frame (at least its own): the
    cost of a run whose parameters the search picks (a second-round sample, a start's polish)."""
    if not design_substeps:
        return search
    return replace(search, substeps=max(search.substeps, int(statistics.median(design_substeps))))


def search_seconds(opt: OptimizeSettings, frames: int, search: RunPlan, design_substeps: Sequence[int]) -> float:
    """The global phase's forward runs on the search grid: each first-round sample at the
    substeps per frame its parameters need there (``design_substeps``, at least ``search``'s:
    a stiffer sample takes proportionally longer; a sample left out, refused beyond the
    substep limit, costs nothing), the later rounds' at typical_sample. Without a design,
    every sample at ``search``'s substeps. A sample runs the search's frames, at most
    ``frames`` (as the search does)."""
    s = opt.search
    sample_frames = min(frames, s.frames or frames)
    later = s.refine + opt.object_round_samples()
    if not design_substeps:
        return (s.samples + later) * run_seconds(search, sample_frames)
    runs = [run_seconds(replace(search, substeps=max(search.substeps, n)), sample_frames) for n in design_substeps]
    return sum(runs) + later * run_seconds(typical_sample(search, design_substeps), sample_frames)


def predicted_seconds(
    opt: OptimizeSettings,
    frames: int,
    variables: int,
    main: RunPlan,
    search: RunPlan,
    searched: bool = False,
    design_substeps: Sequence[int] = (),
    polish_substeps: Sequence[int] = (),
) -> float:
    """The optimisation's seconds with ``main`` the main grid's plan, ``search`` the search
    grid's (the same plan where the search has no grid of its own); ``searched``: what is left
    when the main phase begins (the velocity phase and the search done); ``design_substeps``:
    the search samples' substeps per frame on the search grid (search_seconds). Several starts
    are each polished for ``start_iterations`` on the search grid, compared on the main one,
    and the kept one's polish counts among ``optimize.iterations``: ``polish_substeps``, once
    the search has picked them, each start's substeps per frame on the search grid (at least
    ``search``'s), else ``search.starts`` of them at typical_sample. The iterations of starts
    the search did not find (fewer distinct good samples, or a search the budget cut short)
    go to the main phase: the run's iteration count is fixed."""
    s = opt.search
    polished = s.start_iterations if s is not None and s.starts > 1 else 0
    plans: list[RunPlan] = []  # each start's polish on the search grid
    if polished:
        plans = [replace(search, substeps=max(search.substeps, n)) for n in polish_substeps]
        plans = plans or [typical_sample(search, design_substeps)] * s.starts
    main_iterations = opt.iterations + ((s.starts - len(plans)) * polished if polished else 0)
    seconds = 0.0
    if not searched:
        seconds += opt.estimate_velocity_iterations * iteration_seconds(
            opt, main, opt.estimate_velocity_frames, variables
        )
        if s is not None:
            seconds += search_seconds(opt, frames, search, design_substeps)
    for i in range(polished, main_iterations):
        horizon = min(frames, opt.horizon_start + i * opt.horizon_step) if opt.horizon_start else frames
        seconds += iteration_seconds(opt, main, horizon, variables)
    seconds += diagnostic_runs(variables) * run_seconds(main, frames)
    for plan in plans:
        seconds += polished * iteration_seconds(opt, plan, frames, variables) + run_seconds(main, frames)
    return seconds


def moving_plan(plan: RunPlan, grid: int, search: tuple[int, int]) -> RunPlan:
    """``plan`` (on ``grid`` nodes, its substeps those of the start at rest) with at least the
    substeps the start's motion took on the search's grid, ``search`` = (nodes, substeps),
    scaled by the cells (the CFL step is proportional to the cell size)."""
    nodes, substeps = search
    moving = math.ceil(substeps * (grid - 1) / (nodes - 1))
    return plan if plan.substeps >= moving else replace(plan, substeps=moving)


def choose_grid(
    opt: OptimizeSettings,
    grids: tuple[int, int],
    frames: int,
    variables: int,
    search: tuple[int, int],
    plan_on: Callable[[int], RunPlan],
    budget: float,
    searched: bool = False,
    design_substeps: Sequence[int] = (),
    polish_substeps: Sequence[int] = (),
) -> GridChoice:
    """The finest of the candidate grids between ``grids`` (lowest, highest nodes) whose
    predicted run (``searched``: what is left of it) fits ``budget`` seconds, ``plan_on(nodes)``
    timing each from the coarsest up until one does not fit (or needs more than the substep
    limit); ``search``: the search's grid (nodes) and the substeps per frame the current
    parameters' run took on it; ``design_substeps``, ``polish_substeps``: predicted_seconds'.
    The coarsest when none fits (its prediction above the budget)."""
    search_plan = moving_plan(plan_on(search[0]), search[0], search)
    timed: list[tuple[int, float]] = []
    plans: dict[int, RunPlan] = {}
    for grid in candidate_grids(*grids):
        try:
            plans[grid] = search_plan if grid == search[0] else moving_plan(plan_on(grid), grid, search)
        except SubstepLimitError:
            if not timed:
                raise
            break
        seconds = predicted_seconds(
            opt, frames, variables, plans[grid], search_plan, searched, design_substeps, polish_substeps
        )
        timed.append((grid, seconds))
        if seconds > budget:
            break
    fitting = [(g, s) for g, s in timed if s <= budget]
    grid, seconds = fitting[-1] if fitting else timed[0]
    rest = predicted_seconds(opt, frames, variables, plans[grid], search_plan, True, design_substeps, polish_substeps)
    return GridChoice(grid, seconds, budget, tuple(timed), rest_seconds=rest)


def load_choice(path: Path, key: dict) -> GridChoice | None:
    """The choice saved in ``path`` for ``key`` (the budget, device and config), else None."""
    try:
        data = parse_json(path.read_text())
        if data.get("key") != key:
            return None
        choice = data["choice"]
        return GridChoice(**{**choice, "candidates": tuple((int(g), float(t)) for g, t in choice["candidates"])})
    except (OSError, ValueError, KeyError, TypeError):
        return None


def save_choice(path: Path, key: dict, choice: GridChoice) -> None:
    """``choice`` into ``path`` for ``key``, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({"key": key, "choice": asdict(choice)}, indent=1))
