"""optimize.budget: the main grid a wall time affords, from the device's
timing; the choice kept for a rerun; a budget too small refused before any work."""

import dataclasses
import json
import logging
import re

import pytest

from clflow.pipeline.fit import Optimization
from clflow.pipeline.fit.budget import (
    candidate_grids,
    choose_grid,
    diagnostic_runs,
    moving_plan,
    predicted_seconds,
    run_seconds,
    search_seconds,
    typical_sample,
)
from clflow.pipeline.fit.problem import Problem
from clflow.pipeline.fit.search import SearchDesign
from clflow.pipeline.preflight import GRADIENT_COST, RunPlan
from clflow.pipeline.report import write_report
from clflow.pipeline.runs import write_results
from clflow.pipeline.simulation import SubstepLimitError
from clflow.scene.config import BudgetSettings, OptimizeSettings, SearchSettings
from clflow_datasets.sysid import TRUTH_MARGIN, with_budget
from tests.pipeline.test_preflight import bad_config, one_line_error, run

FRAMES = 10


def cubic_plan(grid: int) -> RunPlan:
    """A device on which a substep costs the cells (1 us per cell) and the stable substeps
    grow with the cells per side, as MPM's do."""
    cells = grid - 1
    return RunPlan(substeps=cells // 4, dt=1e-3, limit="test", particles=8 * cells**3, frames=FRAMES,
                   seconds_per_substep=1e-6 * cells**3)  # fmt: skip


def budgeted(seconds: float, **changes) -> OptimizeSettings:
    return OptimizeSettings(parameters=("youngs_modulus",), iterations=8, budget=BudgetSettings(seconds), **changes)


def test_candidates_climb_from_the_coarsest_to_the_finest_allowed():
    grids = candidate_grids(24, 47)
    assert grids[0] == 24 and grids[-1] == 47 and grids == sorted(set(grids))
    assert candidate_grids(24, 24) == [24]
    assert max(candidate_grids(11, 1000)) == 41  # at most 4x the coarsest's cells


def test_a_run_costs_its_substeps_and_its_flows():
    plan = dataclasses.replace(cubic_plan(25), render_seconds_per_frame=0.5)
    forward = FRAMES * (plan.substeps * plan.seconds_per_substep + 0.5)
    assert run_seconds(plan, FRAMES) == pytest.approx(forward)
    adam = predicted_seconds(budgeted(1.0), FRAMES, 1, plan, plan)
    gradient = FRAMES * (GRADIENT_COST * plan.substeps * plan.seconds_per_substep + 0.5)
    assert adam == pytest.approx(8 * gradient + diagnostic_runs(1) * forward)
    lm = predicted_seconds(budgeted(1.0, method="levenberg_marquardt"), FRAMES, 2, plan, plan)
    assert lm == pytest.approx(8 * 3 * forward + diagnostic_runs(2) * forward)  # point and two Jacobian columns
    coarse = cubic_plan(13)
    searched = budgeted(1.0, search=SearchSettings(samples=32, grid_resolution=13))
    extra = predicted_seconds(searched, FRAMES, 1, plan, coarse) - adam
    assert extra == pytest.approx(32 * run_seconds(coarse, FRAMES))
    # three starts polished for 3 LM iterations on the search grid, compared on the main one,
    # the kept one's 3 among the 8
    starts = dataclasses.replace(searched.search, starts=3, start_iterations=3)
    polishing = budgeted(1.0, method="levenberg_marquardt", search=starts)
    polish = 3 * (3 * 2 * run_seconds(coarse, FRAMES) + forward)
    assert predicted_seconds(polishing, FRAMES, 1, plan, coarse) == pytest.approx(
        32 * run_seconds(coarse, FRAMES) + polish + 5 * 2 * forward + diagnostic_runs(1) * forward
    )


def test_the_search_costs_each_sample_at_its_own_substeps():
    """A stiffer sample needs more substeps: the search's prediction counts each (playdoh's
    search under a 15-min sysid budget ran 255 s where the start's substeps predicted far less)."""
    coarse = cubic_plan(13)  # 3 substeps at rest
    opt = budgeted(1.0, search=SearchSettings(samples=4, refine=2, grid_resolution=13))
    one = run_seconds(coarse, FRAMES)
    assert search_seconds(opt, FRAMES, coarse, ()) == pytest.approx(6 * one)  # no design: the start's
    design = (3, 6, 12, 1)  # substeps of each sample; one below the start's keeps the start's
    first = one * (1 + 2 + 4 + 1)
    typical = run_seconds(typical_sample(coarse, design), FRAMES)
    assert typical_sample(coarse, design).substeps == 4  # the median, 4.5, rounded down
    assert search_seconds(opt, FRAMES, coarse, design) == pytest.approx(first + 2 * typical)
    # parameters of two objects: a round per object, 3 samples per parameter, costed as the second round's
    two = dataclasses.replace(
        opt,
        parameters=("jelly.youngs_modulus", "jelly.poissons_ratio", "heap.friction_angle"),
        search=dataclasses.replace(opt.search, object_samples=3),
    )
    assert two.parameters_by_object() == {"jelly": two.parameters[:2], "heap": two.parameters[2:]}
    assert search_seconds(two, FRAMES, coarse, design) == pytest.approx(first + (2 + 9) * typical)
    refused = design[:2]  # the other two beyond the substep limit: refused unrun
    assert search_seconds(opt, FRAMES, coarse, refused) == pytest.approx(one * (1 + 2) + 2 * one * 4 / 3)
    # samples run the search's frames, never more than the run's (as the search does)
    shorter = dataclasses.replace(opt, search=dataclasses.replace(opt.search, frames=FRAMES // 2))
    assert search_seconds(shorter, FRAMES, coarse, ()) == pytest.approx(6 * run_seconds(coarse, FRAMES // 2))
    longer = dataclasses.replace(opt, search=dataclasses.replace(opt.search, frames=3 * FRAMES))
    assert search_seconds(longer, FRAMES, coarse, ()) == pytest.approx(6 * one)
    plan = cubic_plan(25)
    rest = predicted_seconds(opt, FRAMES, 1, plan, coarse) - search_seconds(opt, FRAMES, coarse, ())
    assert predicted_seconds(opt, FRAMES, 1, plan, coarse, design_substeps=design) == pytest.approx(
        rest + first + 2 * typical
    )
    # the starts' polishes run at parameters the search picks: at the typical sample's substeps
    starts = dataclasses.replace(opt.search, starts=2, start_iterations=3)
    polishing = budgeted(1.0, method="levenberg_marquardt", search=starts)
    extra = predicted_seconds(polishing, FRAMES, 1, plan, coarse, design_substeps=design) - predicted_seconds(
        polishing, FRAMES, 1, plan, coarse
    )
    assert extra == pytest.approx(first + 2 * typical - 6 * one + 2 * 3 * 2 * (typical - one))
    # once the search has picked the starts, each polish at its own parameters' substeps
    picked = (3, 12)  # a start at the start's stiffness and one four times stiffer
    after = predicted_seconds(polishing, FRAMES, 1, plan, coarse, searched=True, polish_substeps=picked)
    before = predicted_seconds(polishing, FRAMES, 1, plan, coarse, searched=True)
    assert after - before == pytest.approx(3 * 2 * (run_seconds(cubic_plan(13), FRAMES) * (4 - 1)))
    # the search found one start, not search.starts: the other's polish is not run and its 3
    # iterations go to the main phase (LM, one variable: 2 runs an iteration there)
    assert predicted_seconds(polishing, FRAMES, 1, plan, coarse, searched=True, polish_substeps=(3,)) == pytest.approx(
        before - 3 * 2 * one - run_seconds(plan, FRAMES) + 3 * 2 * run_seconds(plan, FRAMES)
    )
    assert predicted_seconds(opt, FRAMES, 1, plan, coarse, searched=True, design_substeps=design) == pytest.approx(
        predicted_seconds(opt, FRAMES, 1, plan, coarse, searched=True)
    )  # once searched, the first round's design costs nothing more (no starts to polish here)


def test_the_motion_s_substeps_scale_with_the_cells():
    plan = cubic_plan(49)  # 12 substeps at rest
    assert moving_plan(plan, 49, (25, 30)).substeps == 60  # twice the cells: twice the CFL substeps
    assert moving_plan(plan, 49, (25, 2)) is plan  # the rest's limit is the larger


def test_the_finest_grid_that_fits_is_chosen_and_finer_ones_are_not_built():
    built = []

    def plan_on(grid):
        built.append(grid)
        return cubic_plan(grid)

    opt = budgeted(200.0)
    choice = choose_grid(opt, (25, 97), FRAMES, 1, (25, 6), plan_on, 200.0)
    timed = dict(choice.candidates)
    assert choice.predicted_seconds <= 200.0 < max(timed.values())
    assert all(s <= 200.0 for g, s in timed.items() if g <= choice.grid)
    assert [g for g in timed if g > choice.grid] == [max(timed)]  # the first that does not fit ends the climb
    assert built == [25, *[g for g in timed if g != 25]]
    assert choice.grid == max(g for g, s in timed.items() if s <= 200.0) > 25
    assert choose_grid(budgeted(1e6), (25, 49), FRAMES, 1, (25, 6), cubic_plan, 1e6).grid == 49  # the cap holds
    # when the main phase begins the search is spent: what is left costs less
    searching = budgeted(200.0, search=SearchSettings(samples=32))
    whole = choose_grid(searching, (25, 97), FRAMES, 1, (25, 6), plan_on, 190.0)
    left = choose_grid(searching, (25, 97), FRAMES, 1, (25, 6), plan_on, 190.0, searched=True)
    assert dict(left.candidates)[25] == pytest.approx(timed[25]) and timed[25] < dict(whole.candidates)[25]
    assert left.grid > whole.grid


def test_below_the_coarsest_grid_the_coarsest_is_kept_and_the_error_says_what_it_needs():
    choice = choose_grid(budgeted(1.0), (25, 49), FRAMES, 1, (25, 6), cubic_plan, 1.0)
    assert choice.grid == 25 and choice.predicted_seconds > 1.0 and len(choice.candidates) == 1
    assert re.match(r"optimize.budget: 1 s is too small: .* may choose \(25 nodes\) the optimisation is predicted to take .*; raise the budget to at least", choice.too_small())  # fmt: skip


def test_a_grid_beyond_the_substep_limit_ends_the_climb():
    def plan_on(grid):
        if grid > 31:
            raise SubstepLimitError("too many substeps")
        return cubic_plan(grid)

    assert choose_grid(budgeted(1e6), (25, 49), FRAMES, 1, (25, 6), plan_on, 1e6).grid == 31
    with pytest.raises(SubstepLimitError):
        choose_grid(budgeted(1e6), (37, 49), FRAMES, 1, (37, 6), plan_on, 1e6)


def test_sysid_keeps_the_truth_finer_than_any_main_grid(demo_config):
    cfg = with_budget(demo_config(), 100.0, truth_grid=47)
    assert cfg.optimize.budget == BudgetSettings(100.0, 35)
    assert (47 - 1) / (35 - 1) >= TRUTH_MARGIN


def test_the_config_s_budget_is_checked(quick_demo, tmp_path):
    one_line_error(
        run("optimize", bad_config(quick_demo, tmp_path, "zero", optimize={"budget": {"seconds": 0}})),
        r"optimize.budget.seconds: must be > 0",
    )
    one_line_error(
        run("optimize", bad_config(quick_demo, tmp_path, "cap", optimize={"budget": {"seconds": 60, "max_grid_resolution": 20}})),
        r"optimize.budget.max_grid_resolution: must be 0 or at least the search's grid \(27\)",
    )  # fmt: skip
    res = run("optimize", bad_config(quick_demo, tmp_path, "flag"), "--budget", "soon")
    assert res.exit_code == 2 and "'soon' is not a positive duration" in res.output


def test_a_budget_too_small_is_one_line_before_any_work(quick_demo, tmp_path):
    path = bad_config(quick_demo, tmp_path, "small")
    one_line_error(run("optimize", path, "--budget", "0.01s"), r"optimize.budget: 0.01 s is too small: .* predicted")
    assert not (tmp_path / "out" / "observed_flow.npz").exists()  # the video's flow was never computed


def test_a_budget_chooses_the_grid_when_the_main_phase_begins_and_a_rerun_keeps_it(demo_config, monkeypatch):
    budget = BudgetSettings(seconds=1e5, max_grid_resolution=33)  # the demo's 27 nodes up to 33
    cfg = demo_config(iterations=1)
    cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, budget=budget))
    opt = Optimization(cfg)
    assert opt.grid_choice is None and opt.problem.model_grid == 27  # the run on the coarsest grid fits
    state = opt.run()
    assert opt.grid_choice.grid == opt.problem.model_grid == opt.cfg.simulation.grid_resolution == 33
    assert opt.problem.search_grid == 27 and [g for g, _ in opt.grid_choice.candidates] == candidate_grids(27, 33)
    assert 0 < opt.grid_choice.spent_seconds and opt.grid_choice.budget_seconds < 1e5
    metrics = write_results(opt, state)
    assert metrics["grid"] == {"main": 33, "search": 27} and metrics["budget"]["grid"] == 33
    assert metrics["seconds"] > 0
    page = write_report(cfg.output).read_text()
    assert "<td>grid: main phase, search (nodes)</td><td>33, 27</td>" in page and "main grid predicted" in page
    saved = json.loads((cfg.output / "budget.json").read_text())
    assert saved["choice"]["grid"] == 33 and saved["key"]["device"]

    def untimed(self, grid, z):
        raise AssertionError("a rerun of the same config on the same device times nothing")

    monkeypatch.setattr(Problem, "start_substeps", untimed)
    again = Optimization(cfg)  # its checkpoint, saved on 33 nodes, fits the config of 27
    assert again.grid_choice == opt.grid_choice and again.problem.model_grid == 33
    assert again.run(resume=True).iteration == 1


def test_the_pre_flight_check_costs_each_search_sample_at_its_parameters(demo_config, monkeypatch):
    """The check before any work times the coarsest grid with every first-round sample's own
    substeps: a search box a decade and a half either side of the start reaches stiffer moduli."""
    cfg = demo_config(iterations=1)
    search = SearchSettings(samples=8, decades=1.5)
    cfg = dataclasses.replace(
        cfg, optimize=dataclasses.replace(cfg.optimize, search=search, budget=BudgetSettings(1e5))
    )
    seen = {}

    def recording(*args, **kwargs):
        seen["design"] = kwargs["design_substeps"]
        return choose_grid(*args, **kwargs)

    monkeypatch.setattr("clflow.pipeline.fit.driver.choose_grid", recording)
    opt = Optimization(cfg)
    start = opt.problem.rest_substeps(opt.problem.search_grid, opt.problem.initial_state().z)
    design = seen["design"]
    assert len(design) == 8 and design[0] == start  # the design begins at the start
    assert max(design) > 2 * start  # the stiffest samples need several times the start's substeps


def test_the_main_grid_choice_costs_each_start_s_polish_at_its_parameters(demo_config, monkeypatch):
    """When the main phase begins, the starts the search picked are known: each start's polish
    is costed at the substeps its own parameters ask on the search grid."""
    cfg = demo_config(iterations=2)
    search = SearchSettings(samples=4, starts=2, start_iterations=1, decades=1.5)
    budget = BudgetSettings(1e5, max_grid_resolution=33)
    cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, search=search, budget=budget))
    seen = []

    def recording(*args, **kwargs):
        seen.append(kwargs["polish_substeps"])
        return choose_grid(*args, **kwargs)

    monkeypatch.setattr("clflow.pipeline.fit.driver.choose_grid", recording)
    opt = Optimization(cfg)
    state = opt.run(stop_after=1)
    assert seen[0] == () and len(state.starts) == 2  # before any work the starts are unknown
    own = [opt.problem.rest_substeps(opt.problem.search_grid, z) for z in state.starts]
    assert list(seen[1]) == own, own


def test_a_search_past_its_deadline_ends_with_the_samples_it_has(demo_config, caplog):
    """The search ends once it has used the time the rest of the run needs: here at once,
    after the one sample that must run (the design's first, the start)."""
    cfg = demo_config(iterations=1)
    search = SearchSettings(samples=6, refine=2, decades=1.5)
    cfg = dataclasses.replace(
        cfg, optimize=dataclasses.replace(cfg.optimize, search=search, budget=BudgetSettings(1e5))
    )
    opt = Optimization(cfg)
    assert 9e4 < opt.search.deadline < 1e5  # the budget less the rest's predicted seconds
    opt.search.deadline = 0.0  # as if the samples had taken the budget
    with caplog.at_level(logging.WARNING):
        state = opt.run(stop_after=1)
    assert state.searched and len(state.search) == 1 and state.iteration == 1
    assert "budget: the search stopped after 1 of 8 samples" in caplog.text


def test_a_search_past_its_deadline_in_its_second_round_keeps_what_it_ran(demo_config, caplog, monkeypatch):
    """The deadline passes while the second round runs: the first round's samples and the one
    second-round sample already run are kept, the rest of that round skipped."""
    cfg = demo_config(iterations=1)
    search = SearchSettings(samples=4, refine=4, starts=2, start_iterations=1, decades=1.5)
    cfg = dataclasses.replace(
        cfg, optimize=dataclasses.replace(cfg.optimize, search=search, budget=BudgetSettings(1e5))
    )
    opt = Optimization(cfg)
    first_round_done = SearchDesign.refinement_points

    def deadline_after_one_more(self, regions, z):
        points = first_round_done(self, regions, z)
        real_sample = opt.objective.self_consistent_loss

        def then_late(*args, **kwargs):
            opt.search.deadline = 0.0  # the sample now running is the last
            return real_sample(*args, **kwargs)

        monkeypatch.setattr(opt.objective, "self_consistent_loss", then_late)
        return points

    monkeypatch.setattr(SearchDesign, "refinement_points", deadline_after_one_more)
    with caplog.at_level(logging.WARNING):
        state = opt.run(stop_after=1)
    assert state.searched and len(state.search) == 4 + 1 and state.search[-1].get("around") is not None
    assert "budget: the search stopped after 5 of" in caplog.text
