"""The Levenberg-Marquardt local phase (optimize.method: levenberg_marquardt) on a synthetic
flow model with a known minimiser: convergence, rejected steps, the residuals' loss."""

import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch

from clflow.errors import InputError
from clflow.pipeline.fit import Evaluation, Optimization
from clflow.pipeline.fit.diagnostics import WALK_REACHED, flat
from clflow.pipeline.fit.objective import JITTER_SHIFTS, flow_loss
from clflow.pipeline.fit.state import LM_DAMPING
from clflow.pipeline.fit.steps import LINE_ROUNDS, LM_GAIN_TOLERANCE

# the tests stand in for Objective.evaluate: batches go through it point by point in every plan
pytestmark = pytest.mark.usefixtures("points_one_by_one")

Z_TRUE = math.log10(2e4) + 0.37  # the model's minimiser, 1.37 decades above the demo's start


def evaluation_of(opt, flows, frames, grid=None) -> Evaluation:
    """What ``opt.objective.evaluate`` returns for made-up ``flows`` of the first ``frames`` frames."""
    view = opt.problem.views[0]
    loss = float(flow_loss(opt.cfg, flows, view.observed[:frames], view.weight[:frames]))
    return Evaluation(loss, {}, flows, SimpleNamespace(substeps=1), grid or opt.problem.model_grid)


def fixed_field(opt) -> torch.Tensor:
    """A seeded random field the shape of the observed flows (float64)."""
    return torch.randn(
        opt.problem.views[0].observed.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )


def search_finds(opt, monkeypatch, *youngs_moduli: float) -> None:
    """The global search samples the start, then these log10 Young's moduli, in order."""
    monkeypatch.setattr(
        opt.search.design, "search_points", lambda z0: [dict(z0), *({"youngs_modulus": z} for z in youngs_moduli)]
    )


@pytest.fixture
def lm(demo_config, monkeypatch):
    """The demo's optimiser with simulated flows observed + tanh(z - z_true) x a fixed field:
    a nonlinear residual that vanishes at z_true."""

    def make(iterations=8, curvature=1.0):
        cfg = demo_config(iterations=iterations)
        cfg = dataclasses.replace(
            cfg,
            optimize=dataclasses.replace(cfg.optimize, method="levenberg_marquardt", horizon_start=0),
            flow=dataclasses.replace(cfg.flow, bias_correction="none"),
        )  # flows without a simulation
        opt = Optimization(cfg)
        field = fixed_field(opt)
        calls = []

        def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
            calls.append(dict(z))
            shift = math.tanh(curvature * (z["youngs_modulus"] - Z_TRUE)) / curvature
            flows = [opt.problem.views[0].observed[t] + shift * field[t] for t in range(frames)]
            return evaluation_of(opt, flows, frames, grid)

        monkeypatch.setattr(opt.objective, "evaluate", evaluate)
        return opt, calls

    return make


def test_the_residuals_sum_of_squares_is_the_flow_loss(lm):
    opt, _ = lm()
    ev = opt.objective.evaluate({"youngs_modulus": Z_TRUE + 0.3}, opt.problem.frames)
    assert float((opt.objective.residuals(ev.flows) ** 2).sum()) == pytest.approx(ev.loss, rel=1e-12)


def test_it_converges_from_over_a_decade_off_in_a_few_iterations(lm):
    opt, calls = lm(iterations=12)
    assert opt.problem.initial_state().z["youngs_modulus"] == pytest.approx(Z_TRUE - 1.37)  # the demo's 10x-low start
    state = opt.run()
    assert abs(state.z["youngs_modulus"] - Z_TRUE) < 1e-3
    assert state.history[-1].get("converged") and state.iteration == opt.problem.total_iterations
    losses = [row["loss"] for row in state.history]
    assert losses[-1] < 1e-6 * losses[0] and len(losses) < 12  # stopped by progress, not by the count
    assert len(calls) <= 2 * len(state.history)  # one base run and one per parameter


def test_an_uphill_step_is_rejected_and_the_damping_grows(lm, monkeypatch):
    opt, _ = lm(iterations=2, curvature=1.0)
    state = opt.problem.initial_state()
    variables = ("youngs_modulus",)
    base, J = opt.objective.jacobian(state.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    stepped = opt.steps.lm_step(state, base, J, opt.problem.frames, variables)
    assert stepped.best["z"] == state.z and stepped.damping == pytest.approx(LM_DAMPING)
    uphill = dataclasses.replace(base, loss=2 * base.loss)  # as if the new point were worse
    rejected = opt.steps.lm_step(stepped, uphill, J, opt.problem.frames, variables)
    assert rejected.z == state.z and rejected.damping == pytest.approx(4 * LM_DAMPING)
    assert rejected.iteration == stepped.iteration + 1


def test_a_rejection_quarters_the_trust_region_and_a_new_best_point_doubles_it(lm):
    # along a direction the loss barely sees the damping hardly shortens the step, so a
    # rejected step would come back nearly unchanged without the trust region
    opt, _ = lm(iterations=4)
    variables = ("youngs_modulus",)
    state = opt.problem.initial_state()
    base, J = opt.objective.jacobian(state.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    stepped = opt.steps.lm_step(state, base, J, opt.problem.frames, variables)
    first = abs(stepped.z["youngs_modulus"] - state.z["youngs_modulus"])
    assert stepped.step_scale == pytest.approx(1.0) and first == pytest.approx(1.0)  # the full LM_MAX_STEP
    rejected = opt.steps.lm_step(
        stepped, dataclasses.replace(base, loss=2 * base.loss), J, opt.problem.frames, variables
    )
    assert rejected.step_scale == pytest.approx(0.25) and rejected.z == state.z
    again = opt.steps.lm_step(rejected, base, J, opt.problem.frames, variables)  # back at the best point
    assert (
        again.step_scale == pytest.approx(0.25)
        and abs(again.z["youngs_modulus"] - state.z["youngs_modulus"]) <= 0.25 + 1e-12
    )
    trial, J_trial = opt.objective.jacobian(again.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    accepted = opt.steps.lm_step(again, trial, J_trial, opt.problem.frames, variables)
    assert accepted.best["z"] == again.z and accepted.step_scale == pytest.approx(0.5)


def test_a_rejected_short_step_is_not_tried_again(lm):
    """The radius after a rejection is a quarter of the rejected step, not of a radius it lay
    far inside: the next step from the best point is shorter (the full trophy retried one
    0.06 degree step three times, each a 12 s run, as the radius shrank from 1 towards it)."""
    opt, _ = lm(iterations=4)
    variables = ("youngs_modulus",)
    state = opt.problem.initial_state()
    base, J = opt.objective.jacobian(state.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    best = opt.steps.lm_step(state, base, J, opt.problem.frames, variables)
    short = dataclasses.replace(best, z={"youngs_modulus": state.z["youngs_modulus"] + 0.05})  # inside radius 1
    rejected = opt.steps.lm_step(short, dataclasses.replace(base, loss=2 * base.loss), J, opt.problem.frames, variables)
    assert rejected.z == state.z and rejected.step_scale == pytest.approx(0.05 / 4)
    again = opt.steps.lm_step(rejected, base, J, opt.problem.frames, variables)
    assert abs(again.z["youngs_modulus"] - state.z["youngs_modulus"]) <= 0.05 / 4 + 1e-12


def test_the_trust_region_cuts_the_poorly_determined_component_first(lm):
    """A stiff direction (curvature 1) and one the loss barely sees (1e-4): the Gauss-Newton
    step (0.1, 10) is ten times the radius of 1. Cut to the radius, the step keeps the stiff
    component (scaling the whole step down would leave a tenth of it) and loses the flat one."""
    opt, _ = lm()
    M = torch.diag(torch.tensor([1.0, 1e-4], dtype=torch.float64))
    g = torch.tensor([-0.1, -1e-3], dtype=torch.float64)
    z, variables = {"a": 0.0, "b": 0.0}, ("a", "b")
    assert opt.steps.trust_region_step(M, g, z, variables, 100.0).tolist() == pytest.approx([0.1, 10.0])  # inside
    step = opt.steps.trust_region_step(M, g, z, variables, 1.0)
    assert float(step.norm()) == pytest.approx(1.0, rel=1e-6)
    assert float(step[0]) == pytest.approx(0.1, rel=2e-3) and 0.99 < float(step[1]) < 1.0


def test_a_small_trust_region_does_not_stop_the_run_by_progress(lm):
    """After rejections the radius is a fraction of a decade and any step inside it promises
    little: the stop by progress weighs the model's own step, not the radius' (the 1/1024
    step taken here promises less than the tolerance, so weighing it would have stopped)."""
    opt, _ = lm(iterations=4)
    variables = ("youngs_modulus",)
    state = opt.problem.initial_state()
    base, J = opt.objective.jacobian(state.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    tiny = opt.steps.lm_step(dataclasses.replace(state, step_scale=1 / 1024), base, J, opt.problem.frames, variables)
    assert not tiny.converged
    assert abs(tiny.z["youngs_modulus"] - state.z["youngs_modulus"]) == pytest.approx(1 / 1024)
    r, step = (
        opt.objective.residuals(base.flows),
        torch.tensor([tiny.z["youngs_modulus"] - state.z["youngs_modulus"]], dtype=J.dtype),
    )
    promised = -float(2 * (J.T @ r) @ step + step @ (J.T @ J) @ step)
    assert 0 < promised <= LM_GAIN_TOLERANCE * float(r @ r)


def test_back_at_the_best_point_a_changed_loss_is_taken_not_rejected(lm):
    # back at the best point its loss may come out a little higher than recorded (a checkpoint
    # from before the best point recorded its substeps re-runs it at another step): rejecting
    # it against itself would stall for good
    opt, _ = lm(iterations=2)
    state = opt.problem.initial_state()
    variables = ("youngs_modulus",)
    base, J = opt.objective.jacobian(state.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    stepped = opt.steps.lm_step(state, base, J, opt.problem.frames, variables)
    back = dataclasses.replace(stepped, z=dict(stepped.best["z"]))
    higher = dataclasses.replace(base, loss=base.loss * 1.001)
    again = opt.steps.lm_step(back, higher, J, opt.problem.frames, variables)
    assert again.z != back.z and again.best["loss"] == higher.loss
    assert again.damping == back.damping  # back after a rejection: the raised damping stands


@pytest.mark.parametrize("error_at_trial, accepted", [(0.0, True), (10.0, False)])
def test_a_step_downhill_only_against_the_old_calibration_is_rejected(lm, monkeypatch, error_at_trial, accepted):
    # the estimator's error measured at the new point makes its loss against that error
    # (the search's criterion) higher than the best point's: the step is taken back
    opt, _ = lm(iterations=4)
    opt.cfg.output.mkdir(parents=True, exist_ok=True)
    field = torch.randn(
        opt.problem.views[0].observed.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64
    )
    scale = {"now": 0.0}
    monkeypatch.setattr(type(opt.problem), "corrects_bias", property(lambda self: True))
    monkeypatch.setattr(
        opt.objective, "estimator_errors", lambda result, frames, shifts=None: [scale["now"] * field[:frames]]
    )
    variables = ("youngs_modulus",)
    state = opt.problem.initial_state()
    base, J = opt.objective.jacobian(state.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    stepped = opt.steps.lm_step(state, base, J, opt.problem.frames, variables, calibrate=True)
    assert stepped.calibrated_at["z"] == state.z and stepped.z != state.z
    trial, J_trial = opt.objective.jacobian(stepped.z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    assert trial.loss < stepped.best["loss"]  # downhill against the best point's calibration
    scale["now"] = error_at_trial
    after = opt.steps.lm_step(stepped, trial, J_trial, opt.problem.frames, variables, calibrate=True)
    if accepted:
        assert after.best["z"] == stepped.z and after.calibrated_at["z"] == stepped.z
    else:
        assert after.z == state.z and after.best == stepped.best and after.damping == pytest.approx(4 * stepped.damping)
        assert after.calibrated_at == stepped.calibrated_at
        assert float(opt.objective.errors[0].abs().max()) == 0.0  # the best point's error is back
        again = opt.objective.jacobian(after.z, opt.problem.frames, 1, variables, opt.problem.model_grid)[0]
        assert again.loss == pytest.approx(stepped.best["loss"], rel=1e-12)


def test_a_rejected_trial_leaves_the_best_points_time_step_and_the_result_is_the_best_point(lm, monkeypatch):
    # the first point needs 5 substeps per frame; a step from it runs at its own stable step
    # (asked for at least 1), not at the best point's; the trial needs 7 and is uphill: the
    # next run (the best point again) goes back to the best point's 5, not to the most any
    # run needed
    opt, calls = lm(iterations=2)
    fake = opt.objective.evaluate
    trial, asked = {}, []

    def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
        ev = fake(z, frames, with_grad, min_substeps, variables)
        asked.append(min_substeps)
        if z == trial.get("z"):
            return dataclasses.replace(ev, loss=10 * ev.loss + 1, trajectory=SimpleNamespace(substeps=7))
        return dataclasses.replace(ev, trajectory=SimpleNamespace(substeps=max(5, min_substeps)))

    monkeypatch.setattr(opt.objective, "evaluate", evaluate)
    state, _, _ = opt.iterations.step(opt.problem.initial_state(), 0)
    assert state.z != state.best["z"] and state.substeps == 1 and state.best["substeps"] == 5
    trial["z"], asked[:] = dict(state.z), []
    rejected, _, _ = opt.iterations.step(state, 0)
    assert asked[0] == 1  # the trial's own run
    assert rejected.z == rejected.best["z"] and rejected.substeps == 5
    # a run that ends by its count ends at its best point, not at a step it never ran: the
    # last iteration accepts the trial (now an ordinary point) and computes a step from it
    trial.clear()
    final = opt.run(start=dataclasses.replace(state, iteration=opt.problem.total_iterations - 1))
    assert final.best["z"] == state.z and final.z == final.best["z"] and not final.converged
    assert final.iteration == opt.problem.total_iterations


def test_it_needs_the_l2_loss(tmp_path):
    import json

    from clflow.scene.config import parse_config
    from tests.scene.test_config import GOOD

    (tmp_path / "scene.ply").write_bytes(b"ply\n")
    data = json.loads(json.dumps(GOOD))
    data["optimize"]["method"] = "levenberg_marquardt"
    data["flow"] = {"loss": "charbonnier"}
    with pytest.raises(InputError, match="needs flow.loss l2"):
        parse_config(data, "scene.yaml", tmp_path)


@pytest.mark.parametrize(
    "model, weak, trade_off",
    [
        ("independent", [], False),  # E and nu each move the flow their own way
        ("nu_does_nothing", ["poissons_ratio"], False),
        # a small standard error (many pixels) but a step of 0.1 costs 0.25 % of the loss: flagged
        ("nu_barely_matters", ["poissons_ratio"], False),
        ("only_the_sum_matters", ["youngs_modulus", "poissons_ratio"], True),
    ],
)
def test_identifiability_flags_what_the_video_cannot_tell(demo_config, monkeypatch, model, weak, trade_off):
    cfg = demo_config()
    cfg = dataclasses.replace(
        cfg, optimize=dataclasses.replace(cfg.optimize, parameters=("youngs_modulus", "poissons_ratio"))
    )
    opt = Optimization(cfg)
    g = torch.Generator().manual_seed(1)
    field_e, field_nu = (
        torch.randn(opt.problem.views[0].observed.shape, generator=g, dtype=torch.float64) for _ in range(2)
    )
    noise = 0.01 * torch.randn(opt.problem.views[0].observed.shape, generator=g, dtype=torch.float64)

    def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
        e, nu = z["youngs_modulus"] - Z_TRUE, z["poissons_ratio"]
        shift = {
            "independent": e * field_e + nu * field_nu,
            "nu_does_nothing": e * field_e,
            "nu_barely_matters": e * field_e + 0.005 * nu * field_nu,
            "only_the_sum_matters": (e + nu) * field_e,
        }[model]
        flows = [opt.problem.views[0].observed[t] + noise[t] + shift[t] for t in range(frames)]
        return evaluation_of(opt, flows, frames, grid)

    monkeypatch.setattr(opt.objective, "evaluate", evaluate)
    report = opt.diagnostics.identifiability({"youngs_modulus": Z_TRUE, "poissons_ratio": 0.0}, 1)
    assert sorted(report["weakly_constrained"]) == sorted(weak)
    assert bool(report["trade_offs"]) == trade_off
    if trade_off:
        assert report["trade_offs"][0][2] < -0.95  # E up, nu down: the same flow
    if not weak:
        assert max(report["std_z"].values()) < 1e-3 and min(report["loss_rise"].values()) > 1.0
    if model == "nu_barely_matters":
        assert report["std_z"]["poissons_ratio"] < 0.1 and report["loss_rise"]["poissons_ratio"] < 0.01
    # each weakly constrained variable profiled alone, a z unit either way (cut to nu's typical range)
    assert sorted(report["profile"]) == sorted(weak)
    for name, row in report["profile"].items():
        assert len(row["values"]) == len(row["loss_ratio"]) == 3  # below, at and above the point
        assert row["values"][1] == opt.problem.values({"youngs_modulus": Z_TRUE, "poissons_ratio": 0.0})[name]
        assert row["values"][0] < row["values"][1] < row["values"][2] and row["loss_ratio"][1] == 1.0
    # unresolved: a nu that does nothing; a nu that barely matters over 0.1 raises the loss by
    # a quarter over a whole z unit; E or nu alone breaks a sum that fits
    assert report["unresolved"] == (["poissons_ratio"] if model == "nu_does_nothing" else [])
    if model == "nu_does_nothing":
        assert report["profile"]["poissons_ratio"]["loss_ratio"] == pytest.approx([1.0, 1.0, 1.0], rel=1e-12)
    if model == "nu_barely_matters":
        low, _, high = report["profile"]["poissons_ratio"]["loss_ratio"]
        assert 1.1 < low < 1.5 and 1.1 < high < 1.5


def test_the_grid_check_measures_how_far_a_coarser_grid_moves_the_fit(demo_config, monkeypatch):
    """A check grid whose flows are the model grid's at E 0.3 higher and nu 0.02 lower (in z):
    its best fit lies 0.3 lower in E and 0.02 higher in nu; E is grid-sensitive, nu not."""
    cfg = demo_config()
    cfg = dataclasses.replace(
        cfg, optimize=dataclasses.replace(cfg.optimize, parameters=("youngs_modulus", "poissons_ratio"))
    )
    opt = Optimization(cfg)
    g = torch.Generator().manual_seed(2)
    field_e, field_nu, noise = (
        torch.randn(opt.problem.views[0].observed.shape, generator=g, dtype=torch.float64) for _ in range(3)
    )
    grids = []

    def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
        grid = grid or opt.problem.model_grid
        grids.append(grid)
        coarse = grid != opt.problem.model_grid
        e, nu = z["youngs_modulus"] - Z_TRUE + 0.3 * coarse, z["poissons_ratio"] - 0.02 * coarse
        flows = [
            opt.problem.views[0].observed[t] + 0.01 * noise[t] + e * field_e[t] + nu * field_nu[t]
            for t in range(frames)
        ]
        return evaluation_of(opt, flows, frames, grid)

    monkeypatch.setattr(opt.objective, "evaluate", evaluate)
    report = opt.diagnostics.identifiability({"youngs_modulus": Z_TRUE, "poissons_ratio": 0.0}, 1)
    # the demo has no search grid, and 1.5x coarser its walls leave the object no room: 1.5x finer
    with pytest.raises(InputError, match="does not fit inside simulation.domain"):
        opt.problem.prepared_on(round((opt.problem.model_grid - 1) / 1.5) + 1)
    check = round((opt.problem.model_grid - 1) * 1.5) + 1
    assert report["grids"] == [check, opt.problem.model_grid] and grids.count(check) == 1
    assert report["grid_shift_z"]["youngs_modulus"] == pytest.approx(-0.3, abs=1e-9)
    assert report["grid_shift_z"]["poissons_ratio"] == pytest.approx(0.02, abs=1e-9)
    assert report["grid_sensitive"] == ["youngs_modulus"]
    # the ranges take the model grid's own error by Richardson: h / (H - h) = 3x the shift of a
    # 1.5x finer check; this model ignores the time step, so its check moves nothing
    richardson = 1 / abs((opt.problem.model_grid - 1) / (check - 1) - 1)
    assert report["ranges"]["youngs_modulus"]["grid_z"] == pytest.approx(0.3 * richardson, rel=1e-9)
    assert report["substep_shift_z"]["youngs_modulus"] == pytest.approx(0.0, abs=1e-12)


def test_a_finer_grid_check_widens_the_ranges_where_it_moves_more_than_the_coarser_one(demo_config, monkeypatch):
    """With a coarser search grid the final point also runs on a 1.5x finer grid; each check's
    loss change and fit shift are scaled by its Richardson factor h / |H - h| (2 coarser, 3
    finer), and the larger sets the tolerance and the grid's error: a model whose convergence
    is not monotone (the finer grid moves E and the loss more than the coarser one) gets
    wider ranges than the coarser check alone would give."""
    cfg = demo_config()
    cfg = dataclasses.replace(
        cfg, optimize=dataclasses.replace(cfg.optimize, parameters=("youngs_modulus", "poissons_ratio"))
    )
    opt = Optimization(cfg)
    opt.problem.search_grid = round((opt.problem.model_grid - 1) / 1.5) + 1
    monkeypatch.setattr(opt.problem, "prepared_on", lambda grid: None)  # room for the object on the coarser grid
    finer = round((opt.problem.model_grid - 1) * 1.5) + 1
    g = torch.Generator().manual_seed(4)
    field_e, field_nu, noise, error = (
        torch.randn(opt.problem.views[0].observed.shape, generator=g, dtype=torch.float64) for _ in range(4)
    )
    grids = []

    def report_with(finer_error, fails=()):
        # E's best fit lies 0.01 higher on the coarser grid and finer_error higher on the finer one;
        # the finer grid's model error is a third of the coarser one's, and grows with finer_error
        def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
            grid = grid or opt.problem.model_grid
            grids.append(grid)
            if grid in fails:
                raise MemoryError("no room for the grid")
            moved = {opt.problem.search_grid: 0.01, finer: finer_error}.get(grid, 0.0)
            model_error = 0.05 * {opt.problem.search_grid: 1.0, finer: 0.3 + 10 * finer_error}.get(grid, 0.0)
            e, nu = z["youngs_modulus"] - Z_TRUE - moved, z["poissons_ratio"]
            flows = [opt.problem.views[0].observed[t] + 0.05 * noise[t] + model_error * error[t] + e * field_e[t]
                     + nu * field_nu[t] for t in range(frames)]  # fmt: skip
            return evaluation_of(opt, flows, frames, grid)

        monkeypatch.setattr(opt.objective, "evaluate", evaluate)
        grids.clear()
        return opt.diagnostics.identifiability({"youngs_modulus": Z_TRUE, "poissons_ratio": 0.0}, 1)

    quiet, loud = report_with(0.0), report_with(0.1)
    assert grids.count(opt.problem.search_grid) == grids.count(finer) == 1  # one run on each check grid
    for report in (quiet, loud):
        coarse_check, finer_check = report["grid_checks"]
        assert [coarse_check["nodes"], finer_check["nodes"]] == [opt.problem.search_grid, finer]
        assert report["grids"] == [
            opt.problem.search_grid,
            opt.problem.model_grid,
        ]  # the table's grid-sensitive note: the coarser
        assert coarse_check["richardson"] == pytest.approx(
            1 / ((opt.problem.model_grid - 1) / (opt.problem.search_grid - 1) - 1)
        )
        assert finer_check["richardson"] == pytest.approx(1 / (1 - (opt.problem.model_grid - 1) / (finer - 1)))
        scaled = [c["richardson"] * c["loss_change"] for c in (coarse_check, finer_check)]
        assert report["loss_tolerance"] == pytest.approx(max(scaled), rel=1e-9)  # the time step moves nothing here
        e_moves = [c["richardson"] * abs(c["shift_z"]["youngs_modulus"]) for c in (coarse_check, finer_check)]
        assert report["ranges"]["youngs_modulus"]["grid_z"] == pytest.approx(max(e_moves), rel=1e-9)
        assert coarse_check["shift_z"]["youngs_modulus"] == pytest.approx(0.01, abs=1e-3)
    # the quiet finer grid is the better model: the coarser check sets the tolerance and E's
    # grid error; the loud one sets both, and the ranges widen
    coarse_check, finer_check = quiet["grid_checks"]
    assert (
        coarse_check["richardson"] * coarse_check["loss_change"]
        > finer_check["richardson"] * finer_check["loss_change"]
    )
    assert quiet["loss_tolerance"] == pytest.approx(coarse_check["richardson"] * coarse_check["loss_change"])
    assert finer_check["shift_z"]["youngs_modulus"] == pytest.approx(0.0, abs=1e-3)
    coarse_check, finer_check = loud["grid_checks"]
    assert finer_check["shift_z"]["youngs_modulus"] == pytest.approx(0.1, abs=1e-3)
    assert loud["loss_tolerance"] == pytest.approx(finer_check["richardson"] * finer_check["loss_change"])
    assert loud["loss_tolerance"] > 2 * quiet["loss_tolerance"]
    assert loud["ranges"]["youngs_modulus"]["grid_z"] == pytest.approx(finer_check["richardson"] * 0.1, rel=0.02)
    for name in ("youngs_modulus", "poissons_ratio"):
        q, w = quiet["ranges"][name], loud["ranges"][name]
        assert w["high"] > q["high"] and w["low"] < q["low"]
    # a check that cannot run (out of memory on the finer grid) is recorded and left out
    failed = report_with(0.1, fails=(finer,))
    assert [c["ran"] for c in failed["grid_checks"]] == [True, False]
    assert failed["loss_tolerance"] == pytest.approx(quiet["loss_tolerance"])


def test_a_range_reaches_out_to_where_a_flattening_loss_crosses_the_tolerance(demo_config, monkeypatch):
    """E's flow saturates (tanh) away from the fit, so the loss rises slower than its curvature
    there says: the measured upper end lies beyond the Gauss-Newton one, and the loss there is
    the tolerance's; nu's flow is linear, and its range stays the Gauss-Newton one."""
    cfg = demo_config()
    cfg = dataclasses.replace(
        cfg, optimize=dataclasses.replace(cfg.optimize, parameters=("youngs_modulus", "poissons_ratio"))
    )
    opt = Optimization(cfg)
    g = torch.Generator().manual_seed(3)
    field_e, field_nu, noise, coarse_noise = (
        torch.randn(opt.problem.views[0].observed.shape, generator=g, dtype=torch.float64) for _ in range(4)
    )

    def flows_at(z, grid=None):
        dz = z["youngs_modulus"] - Z_TRUE
        e, nu = 0.02 * math.tanh(dz / 0.02) + 0.15 * dz, z["poissons_ratio"]
        coarse = (grid or opt.problem.model_grid) != opt.problem.model_grid  # model error: the loss moves by ~10 %
        return [opt.problem.views[0].observed[t] + 0.05 * (noise[t] + 0.3 * coarse * coarse_noise[t]) + e * field_e[t]
                + nu * field_nu[t] for t in range(opt.problem.frames)]  # fmt: skip

    def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
        return evaluation_of(opt, flows_at(z, grid)[:frames], frames, grid)

    monkeypatch.setattr(opt.objective, "evaluate", evaluate)
    z = {"youngs_modulus": Z_TRUE, "poissons_ratio": 0.0}
    report = opt.diagnostics.identifiability(z, 1)
    limit = 1 + report["loss_tolerance"]
    e, nu = report["ranges"]["youngs_modulus"], report["ranges"]["poissons_ratio"]
    high = math.log10(e["high"]) - Z_TRUE
    assert 0.05 < report["loss_tolerance"] < 1.0
    assert high > 1.5 * e["profile_z"] and e["walked_z"][1] == pytest.approx(high)
    runs = [tuple(run) for run in e["walk_loss_ratio"][1]]
    first_beyond = next((i for i, (_, r) in enumerate(runs) if r > limit), len(runs))
    assert all(a[0] < b[0] for a, b in zip(runs[:first_beyond], runs[1:first_beyond]))  # out until beyond
    inside = max((run for run in runs if run[1] <= limit), default=None)
    beyond = min((run for run in runs if run[1] > limit), default=None)
    reached = 1 + WALK_REACHED * report["loss_tolerance"]
    if beyond is not None and inside[1] < reached:  # ended by the chord across the last bracket
        assert high == pytest.approx(
            inside[0] + (beyond[0] - inside[0]) * (limit - inside[1]) / (beyond[1] - inside[1])
        )
    else:  # ended on a run that reached 90 % of the tolerance
        assert high == pytest.approx(inside[0]) and inside[1] >= reached
    loss = lambda dz: float(evaluate({**z, "youngs_modulus": Z_TRUE + dz}, opt.problem.frames).loss)  # noqa: E731
    assert loss(high) / loss(0.0) < 1.01 * limit  # nu held here, refitted in the walk: 1 % either way
    assert nu["walked_z"] == pytest.approx([nu["profile_z"], nu["profile_z"]], rel=0.01)
    # a search whose highest E fits as well as its best (within the tolerance times the fit's
    # loss) opens that side, which is then not walked
    fit, within = loss(0.0), 0.5 * report["loss_tolerance"]
    search = [
        {"z": {**z, "youngs_modulus": Z_TRUE + dz}, "loss": fit * ratio}
        for dz, ratio in [(0, 1.0), (1, 1 + within), (-1, 9.0)]
    ]
    e = opt.diagnostics.identifiability(z, 1, search)["ranges"]["youngs_modulus"]
    assert e["high"] is None and e["walked_z"][1] is None and e["walk_loss_ratio"][1] == []
    assert e["low"] is not None and e["walk_loss_ratio"][0]


def test_a_rejected_step_goes_back_to_the_best_point_without_new_runs(lm):
    opt, calls = lm(iterations=2)
    variables = ("youngs_modulus",)
    best_z, trial_z = {"youngs_modulus": Z_TRUE - 1.0}, {"youngs_modulus": Z_TRUE - 0.5}
    opt.objective.jacobian(best_z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    opt.objective.jacobian(trial_z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    runs = len(calls)
    opt.objective.jacobian(best_z, opt.problem.frames, 1, variables, opt.problem.model_grid)  # back after a rejection
    opt.objective.jacobian(
        {"youngs_modulus": Z_TRUE - 0.7}, opt.problem.frames, 1, variables, opt.problem.model_grid
    )  # a shorter step, rejected too
    assert len(calls) == runs + 2
    opt.objective.jacobian(best_z, opt.problem.frames, 1, variables, opt.problem.model_grid)
    assert len(calls) == runs + 2


def test_it_stops_when_the_model_promises_no_progress(lm):
    opt, calls = lm(iterations=12)
    state = opt.problem.initial_state()
    state.z = {"youngs_modulus": Z_TRUE}  # at the minimiser: r = 0, nothing to gain
    state = opt.run(start=state)
    assert state.converged and state.history[-1].get("converged") and len(state.history) == 1


Z_FALSE = Z_TRUE - 1.2  # a local minimum whose residual stays 0.5 x the field


def with_starts(cfg, starts: int, **search):
    """``cfg`` optimised by Levenberg-Marquardt after a 3-sample search polishing ``starts``
    starts for 3 iterations each (``search``: more SearchSettings), without bias correction."""
    from clflow.scene.config import SearchSettings

    return dataclasses.replace(
        cfg,
        flow=dataclasses.replace(cfg.flow, bias_correction="none"),
        optimize=dataclasses.replace(
            cfg.optimize,
            method="levenberg_marquardt",
            horizon_start=0,
            search=SearchSettings(samples=3, starts=starts, start_iterations=3, **search),
        ),
    )


@pytest.mark.parametrize("starts", [1, 2])
def test_several_starts_are_polished_and_the_best_is_kept(demo_config, monkeypatch, starts):
    opt = Optimization(with_starts(demo_config(iterations=6), starts))
    field = fixed_field(opt)

    def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
        e = z["youngs_modulus"]  # two basins: the true one (residual 0) and a false one (0.5)
        shift = min(math.sqrt((e - Z_TRUE) ** 2 + 1e-8), math.sqrt((e - Z_FALSE) ** 2 + 1e-8) + 0.5)
        flows = [opt.problem.views[0].observed[t] + shift * field[t] for t in range(frames)]
        return evaluation_of(opt, flows, frames, grid)

    monkeypatch.setattr(opt.objective, "evaluate", evaluate)
    # the search's best sample lies in the false basin, the runner-up in the true one
    search_finds(opt, monkeypatch, Z_FALSE + 0.05, Z_TRUE + 0.6)
    assert opt.problem.total_iterations == 6 + (starts - 1) * 3
    state = opt.run()
    if starts == 1:
        assert abs(state.z["youngs_modulus"] - Z_FALSE) < 0.1 and not state.polished  # stuck in the false basin
    else:
        assert [round(s["youngs_modulus"], 6) for s in state.starts] == [
            round(Z_FALSE + 0.05, 6),
            round(Z_TRUE + 0.6, 6),
        ]
        assert len(state.polished) == 2 and state.polished[1]["loss"] < state.polished[0]["loss"]
        assert {r.get("start") for r in state.history} == {0, 1, None}
        assert abs(state.z["youngs_modulus"] - Z_TRUE) < 0.05  # (the kinked model: FD steps of 0.01)


def test_a_coarse_search_grid_runs_the_global_phase_and_the_main_grid_picks_the_start(demo_config, monkeypatch):
    """optimize.search.grid_resolution: the search and the starts' polish run on the coarse
    grid, the main phase on the simulation's; the start kept is the one whose loss is least
    on the main grid, though another is deeper on the coarse one (a coarse model's bias)."""
    cfg = demo_config(iterations=6)
    fine = cfg.simulation.grid_resolution
    coarse = fine - 3
    opt = Optimization(with_starts(cfg, 2, grid_resolution=coarse))
    assert (opt.problem.search_grid, opt.problem.model_grid) == (coarse, fine)
    assert opt.problem._prepared[coarse].setup.grid.dx > opt.problem._prepared[fine].setup.grid.dx
    field = fixed_field(opt)
    grids = []

    def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
        grid = grid or opt.problem.model_grid
        grids.append(grid)
        e = z["youngs_modulus"]  # two basins: on the coarse grid the false one is the deeper
        to_true, to_false = math.sqrt((e - Z_TRUE) ** 2 + 1e-8), math.sqrt((e - Z_FALSE) ** 2 + 1e-8)
        shift = min(to_true + 0.02, to_false) if grid == coarse else min(to_true, to_false + 0.5)
        flows = [opt.problem.views[0].observed[t] + shift * field[t] for t in range(frames)]
        return evaluation_of(opt, flows, frames, grid)

    monkeypatch.setattr(opt.objective, "evaluate", evaluate)
    search_finds(opt, monkeypatch, Z_FALSE + 0.05, Z_TRUE + 0.05)
    state = opt.run()
    assert {r["grid"] for r in state.search} == {coarse}
    assert {r["grid"] for r in state.history if "start" in r} == {coarse}
    assert {r["grid"] for r in state.history if "start" not in r} == {fine}
    first_main = next(i for i, r in enumerate(state.history) if "start" not in r)
    assert set(grids[: grids.index(fine)]) == {coarse} and first_main > 0
    false, true = state.polished  # the search ranks the false basin's sample first
    assert false["loss"] < true["loss"] and true["model_loss"] < false["model_loss"]
    assert abs(state.z["youngs_modulus"] - Z_TRUE) < 0.05


def test_a_variable_on_its_box_edge_is_held_and_the_rest_solved_again(lm, monkeypatch):
    opt, _ = lm()
    monkeypatch.setattr(opt.problem, "local_box", lambda: {"a": (0.0, 1.0), "b": (0.0, 1.0)})
    M = torch.tensor([[2.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
    g = torch.tensor([1.0, -1.0], dtype=torch.float64)  # free step: (-1, 1)
    inside = opt.steps.bounded_step(M, g, {"a": 0.5, "b": 0.5}, ("a", "b"))
    assert inside.tolist() == pytest.approx([-1.0, 1.0])
    # a on its lower edge, pushed out: held, and b's step is that of b alone, -g_b / M_bb
    assert opt.steps.bounded_step(M, g, {"a": 0.0, "b": 0.5}, ("a", "b")).tolist() == pytest.approx([0.0, 0.5])
    # then b on its upper edge, pushed out too: nothing moves (the model promises nothing: converged)
    assert opt.steps.bounded_step(M, g, {"a": 0.0, "b": 1.0}, ("a", "b")).tolist() == [0.0, 0.0]
    # an edge the step points away from holds nothing
    assert opt.steps.bounded_step(M, g, {"a": 1.0, "b": 0.0}, ("a", "b")).tolist() == pytest.approx([-1.0, 1.0])


def test_the_profile_calls_flat_only_a_loss_that_neither_rises_nor_falls(lm):
    """A decade below the minimiser of the tanh model, a decade up lowers the loss: not
    flat (the point is no minimum along E). Above the typical range the box is widened to
    hold the point, and only the side below is run."""
    opt, _ = lm()
    z = {"youngs_modulus": Z_TRUE - 1.0}
    ev = opt.objective.evaluate(z, opt.problem.frames)
    row = opt.diagnostics.profile(z, 1, ["youngs_modulus"], float((opt.objective.residuals(ev.flows) ** 2).sum()))[
        "youngs_modulus"
    ]
    low, at, high = row["loss_ratio"]
    assert low > 1.1 and at == 1.0 and high < 0.9 and not flat(row)
    assert flat({"loss_ratio": [1.05, 1.0, 0.95]}) and not flat({"loss_ratio": [1.05, 1.0, 0.5]})  # a fall
    assert not flat({"loss_ratio": [1.0, 1.0, None]}) and not flat({"loss_ratio": [1.0]})  # a failed run; no side
    above = {"youngs_modulus": opt.problem.typical_box("youngs_modulus")[1] + 0.5}
    row = opt.diagnostics.profile(above, 1, ["youngs_modulus"], 1.0)["youngs_modulus"]
    assert len(row["values"]) == 2 and row["values"][1] == opt.problem.values(above)["youngs_modulus"]
    assert opt.diagnostics.profile(z, 1, ["velocity_x"], 1.0) == {}  # a velocity component is not profiled


def test_a_rejected_trial_says_so_and_the_run_says_why_it_stopped(lm, monkeypatch, caplog):
    """An overshooting model: the first step lands uphill. Its row is marked rejected (its
    loss is the trial's, not a point the run moved to) and the run logs why it ended."""
    from clflow.pipeline.runs import format_row

    opt, _ = lm(iterations=4)
    z0, field = opt.problem.initial_state().z["youngs_modulus"], fixed_field(opt)

    def evaluate(z, frames, with_grad=True, min_substeps=1, variables=None, grid=None):
        d = z["youngs_modulus"] - z0
        flows = [opt.problem.views[0].observed[t] + (1 + d + 10 * d * d) * field[t] for t in range(frames)]
        return evaluation_of(opt, flows, frames, grid)

    monkeypatch.setattr(opt.objective, "evaluate", evaluate)
    with caplog.at_level("INFO", logger="clflow.pipeline.fit.driver"):
        state = opt.run()
    rejected = [row for row in state.history if row.get("rejected")]
    assert rejected and all(row["loss"] > state.history[0]["loss"] for row in rejected)
    assert "rejected (trial " in format_row(rejected[0])
    assert not state.history[0].get("rejected")
    stops = [r.getMessage() for r in caplog.records if "stopped" in r.getMessage()]
    assert len(stops) == 1 and ("converged" in stops[0] or "ran its 4 iteration(s)" in stops[0])


def test_a_weakly_constrained_parameter_is_told_by_the_reason_that_flagged_it():
    from clflow.pipeline.fit.results import weak_reason

    assert weak_reason(0.35, 0.5) == "standard error 0.35 in the optimiser's units, above 0.1 (a lower bound)"
    small_rise = weak_reason(0.009, 0.004)  # a tiny standard error, yet the loss barely moves: say that
    assert (
        small_rise == "a step of 0.1 in the optimiser's units, the others refitted, raises the loss by 0.4 %, under 1 %"
    )


def test_after_lm_stops_a_line_search_of_the_own_calibration_loss_goes_on(lm, monkeypatch, caplog):
    # the estimator errs by -0.9 x the simulated motion: calibrated at C, LM's model has its
    # minimum where tanh(z - z_true) = 0.9 tanh(C - z_true), so each calibration gains only
    # a tenth; the own-calibration loss (0.1 tanh(z - z_true))^2 |field|^2 falls all the way
    # to z_true, and the line search after LM's last iteration follows it
    opt, calls = lm(iterations=4)
    observed, fake = opt.problem.views[0].observed, opt.objective.evaluate
    monkeypatch.setattr(
        opt.objective, "evaluate", lambda *args, **kwargs: opt.objective.rescored(fake(*args, **kwargs))
    )  # the targets'
    monkeypatch.setattr(type(opt.problem), "corrects_bias", property(lambda self: True))
    monkeypatch.setattr(
        opt.objective,
        "estimator_errors",
        lambda result, frames, shifts=None: [-0.9 * (torch.stack(result.flows[:frames]) - observed[:frames])],
    )
    with caplog.at_level("INFO", logger="clflow.pipeline.fit.steps"):
        state = opt.run()
    searched = state.line_search
    assert searched is not None and searched["moved"]
    lm_end = searched["from"]["youngs_modulus"]
    assert lm_end < 10 ** (Z_TRUE - 0.3)  # LM stopped well short of the truth
    assert abs(state.z["youngs_modulus"] - Z_TRUE) < abs(math.log10(lm_end) - Z_TRUE)  # nearer the truth
    assert searched["loss"] <= searched["loss_from"] * (1 - 1e-3)
    # it searched again from each point it moved to, until a round stayed (or its rounds ran out)
    rounds = searched["rounds"]
    assert rounds[0]["moved"] and all(r["moved"] for r in rounds[:-1])
    assert not rounds[-1]["moved"] or len(rounds) == LINE_ROUNDS
    assert state.best["z"] == state.z and state.best["loss"] == searched["loss"]
    assert state.calibrated_at["z"] == state.z  # the final point's own calibration, over the shifts
    assert state.calibrated_at["shifts"] == [list(shift) for shift in JITTER_SHIFTS]
    final = opt.objective.jacobian(
        state.z, opt.problem.frames, state.substeps, ("youngs_modulus",), opt.problem.model_grid
    )[0]
    assert opt.objective.rescored(final).loss == pytest.approx(searched["loss"], rel=1e-9)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("line search of the own")]
    assert len(lines) == 1 and " to {" in lines[0]
    # done once: a resumed finished run does not search again
    before = len(calls)
    again = opt.run(resume=True)
    assert again.z == state.z and len(calls) == before


def test_the_line_search_holds_a_variable_the_video_does_not_pin_down(lm, monkeypatch, caplog):
    # as above, but the estimator's error carries a large offset that no parameter explains
    # (model error): a step of 0.1 in z raises the loss by far under 1 %, so Young's modulus
    # is weakly constrained and the line search leaves it where LM stopped
    opt, calls = lm(iterations=4)
    observed, fake = opt.problem.views[0].observed, opt.objective.evaluate
    offset = 40.0 * torch.ones_like(observed)
    monkeypatch.setattr(
        opt.objective, "evaluate", lambda *args, **kwargs: opt.objective.rescored(fake(*args, **kwargs))
    )
    monkeypatch.setattr(type(opt.problem), "corrects_bias", property(lambda self: True))
    monkeypatch.setattr(
        opt.objective,
        "estimator_errors",
        lambda result, frames, shifts=None: [
            -0.9 * (torch.stack(result.flows[:frames]) - observed[:frames]) - offset[:frames]
        ],
    )
    with caplog.at_level("INFO", logger="clflow.pipeline.fit.steps"):
        state = opt.run()
    searched = state.line_search
    assert searched["held"] == ["youngs_modulus"] and not searched["moved"]
    assert state.z == state.best["z"] and opt.problem.values(state.z) == searched["from"]
    assert state.best["loss"] == searched["loss_from"]  # scored against the shift-mean error
    assert state.calibrated_at["shifts"] == [list(shift) for shift in JITTER_SHIFTS]
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("line search of the own")]
    assert lines == ["line search of the own-calibration loss: none of ['youngs_modulus'] is pinned down, all stay"]
