"""The optimiser's parts (clflow.pipeline.fit) on their own, with small inputs: no scene, no
simulation, no Optimization; each part is given stand-ins of its collaborators with only
what it reads of them."""

import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch

from clflow.pipeline.fit.diagnostics import (
    PROFILE_RISE,
    RANGE_Z,
    WALK_BRACKET,
    WALK_REACHED,
    WALK_RUNS,
    fit_shift,
    flat,
    frame_robust_covariance,
    parameter_range,
    search_extent,
    walk_end,
    walk_in_lockstep,
    walk_steps,
    widen_by_search,
)
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.search import Search, SearchDesign
from clflow.pipeline.fit.state import LM_DAMPING, UnstableRun
from clflow.pipeline.fit.steps import (
    LINE_GAIN,
    LINE_MAX_GROWTH,
    LINE_STEP,
    LM_MAX_STEP,
    Steps,
    line_search,
    phase_of,
    rate_schedule,
)


def boxed_steps(box: dict[str, tuple[float, float]]) -> Steps:
    """Steps of a problem with a local box (z units) and nothing else."""
    return Steps(SimpleNamespace(problem=SimpleNamespace(local_box=lambda: box)))


M = torch.tensor([[4.0, 0.5], [0.5, 0.1]], dtype=torch.float64)  # b is poorly determined
G = torch.tensor([-2.0, -0.5], dtype=torch.float64)


def test_bounded_step_solves_the_model_when_no_edge_is_in_the_way():
    step = boxed_steps({}).bounded_step(M, G, {"a": 0.0, "b": 0.0}, ("a", "b"))
    torch.testing.assert_close(M @ step, -G)


def test_bounded_step_holds_a_variable_on_its_edge_and_solves_the_rest_without_it():
    z = {"a": 0.0, "b": 1.0}  # b on its upper edge; the free solution pushes it up
    assert float(boxed_steps({}).bounded_step(M, G, z, ("a", "b"))[1]) > 0
    step = boxed_steps({"b": (-1.0, 1.0)}).bounded_step(M, G, z, ("a", "b"))
    assert float(step[1]) == 0.0 and float(step[0]) == pytest.approx(-float(G[0]) / float(M[0, 0]))


def test_the_trust_region_cuts_the_poorly_determined_component_most():
    steps, z = boxed_steps({}), {"a": 0.0, "b": 0.0}
    free = steps.bounded_step(M, G, z, ("a", "b"))
    cut = steps.trust_region_step(M, G, z, ("a", "b"), radius=0.1 * float(free.norm()))
    assert float(cut.norm()) == pytest.approx(0.1 * float(free.norm()), rel=1e-6)
    assert abs(float(cut[1] / free[1])) < abs(float(cut[0] / free[0]))  # not a uniform scaling


def test_phases_and_the_learning_rate_schedule():
    opt = SimpleNamespace(estimate_velocity_iterations=3, iterations=10, final_rate=0.1)
    assert [phase_of(opt, k)[:2] for k in (0, 2, 3, 12)] == [("velocity", 0), ("velocity", 2), ("main", 0), ("main", 9)]
    assert rate_schedule(opt, 0) == 1.0 and rate_schedule(opt, 9) == pytest.approx(0.1)
    assert rate_schedule(opt, 4) > rate_schedule(opt, 5)  # falls all the way


@pytest.mark.parametrize(
    "ratios, is_flat",
    [([1.05, 0.95], True), ([1.0 + PROFILE_RISE / 2, 1.0 - PROFILE_RISE / 2], True), ([1.5, 1.01], False), ([0.5, 1.0], False),
     ([1.02], False), ([1.0, None], False)],
)  # fmt: skip
def test_a_profile_is_flat_only_when_both_moves_change_the_loss_little(ratios, is_flat):
    assert flat({"loss_ratio": ratios}) is is_flat


def grid_design(starts: int, refine: int, samples: int = 4) -> SearchDesign:
    """The design of a problem with a fixed box, parameters and counts (what neighbourhoods
    and refinement read)."""
    search = SimpleNamespace(starts=starts, refine=refine, samples=samples)
    return SearchDesign(
        SimpleNamespace(
            cfg=SimpleNamespace(optimize=SimpleNamespace(search=search)),
            params={"e": None, "nu": None},
            search_box=lambda z0: {"e": (0.0, 4.0), "nu": (0.0, 1.0)},
        )
    )


def test_second_round_regions_are_the_best_distinct_samples_cut_to_the_box():
    rows = [
        {"z": {"e": 1.0, "nu": 0.5}, "loss": 0.1},
        {"z": {"e": 1.1, "nu": 0.5}, "loss": 0.2},  # inside the best one's box: not a centre
        {"z": {"e": 3.9, "nu": 0.9}, "loss": 0.3},
        {"z": {"e": 2.0, "nu": 0.1}, "loss": None},  # a failed sample
    ]
    regions = grid_design(starts=2, refine=5).neighbourhoods(rows, {"e": 0.0, "nu": 0.0})
    assert [i for i, _ in regions] == [0, 2]
    spacing = 4.0 * 4**-0.5  # the box's width / first-round samples^(1/parameters)
    assert regions[0][1]["e"] == pytest.approx((1.0 - spacing / 2, 1.0 + spacing / 2))
    assert regions[1][1]["e"][1] == 4.0 and regions[1][1]["nu"][1] == 1.0  # cut to the search box
    points = grid_design(starts=2, refine=5).refinement_points(regions, {"e": 0.0, "nu": 0.0})
    assert [i for i, _ in points] == [0, 0, 0, 2, 2]  # 5 shared, the first region one more
    for i, z in points:
        assert all(lo <= z[n] <= hi for n, (lo, hi) in dict(regions)[i].items())


class SeparableObjective:
    """The objective of two objects' parameters (jelly's log10 E in [2, 6], heap's friction
    angle in [20, 50]) whose loss is one narrow well per object: 2 - exp(-(d/w)^2) - exp(-(e/w')^2)."""

    def __init__(self, object_samples: int):
        from clflow.scene.config import OptimizeSettings, SearchSettings

        search = SearchSettings(samples=8, refine=0, starts=1, object_samples=object_samples)
        optimize = OptimizeSettings(parameters=("jelly.youngs_modulus", "heap.friction_angle"), search=search)
        self.problem = SimpleNamespace(
            cfg=SimpleNamespace(optimize=optimize),
            params={"jelly.youngs_modulus": None, "heap.friction_angle": None},
            frames=4,
            search_grid=24,
            search_box=lambda z0: {"jelly.youngs_modulus": (2.0, 6.0), "heap.friction_angle": (20.0, 50.0)},
            values=dict,
        )

    def evaluate(self, z, frames, with_grad=True, min_substeps=1, grid=None):
        jelly = math.exp(-(((z["jelly.youngs_modulus"] - 4.7) / 0.25) ** 2))
        heap = math.exp(-(((z["heap.friction_angle"] - 37.0) / 2.5) ** 2))
        return SimpleNamespace(loss=2.0 - jelly - heap)

    def self_consistent_loss(self, result, frames):
        return result.loss

    evaluate_batch = Objective.evaluate_batch  # the real batch, over this evaluate


def separable_search(object_samples: int) -> Search:
    """The search of :class:`SeparableObjective`, its checkpoint a stand-in that saves nothing."""
    return Search(SeparableObjective(object_samples), SimpleNamespace(save=lambda state: None), started=0.0)


def test_object_rounds_find_each_objects_narrow_well_that_the_joint_design_misses():
    from clflow.pipeline.fit.state import OptimizerState

    z0 = {"jelly.youngs_modulus": 3.0, "heap.friction_angle": 25.0}
    begin = OptimizerState(z=z0, iteration=0, m={}, v={})
    joint = separable_search(object_samples=0).global_search(begin)
    assert len(joint.search) == 8
    assert min(r["loss"] for r in joint.search) > 1.0  # 8 samples land in neither well at once

    state = separable_search(object_samples=8).global_search(begin)
    rows = state.search
    assert len(rows) == 8 + 8 + 8 and [r.get("object") for r in rows[8:]] == ["jelly"] * 8 + ["heap"] * 8
    held = min(rows[:8], key=lambda r: r["loss"])["z"]
    assert all(r["z"]["heap.friction_angle"] == held["heap.friction_angle"] for r in rows[8:16])
    jelly_best = min(rows[:16], key=lambda r: r["loss"])["z"]
    assert all(r["z"]["jelly.youngs_modulus"] == jelly_best["jelly.youngs_modulus"] for r in rows[16:])
    # each within its well's width (an object round spaces its 8 samples 0.5 decade, 3.75 deg apart)
    assert abs(state.z["jelly.youngs_modulus"] - 4.7) < 0.25 and abs(state.z["heap.friction_angle"] - 37.0) < 2.5
    for cut in (11, 19):  # interrupted in either object's round, a resumed search is the same
        resumed = separable_search(object_samples=8).global_search(dataclasses.replace(begin, search=rows[:cut]))
        assert [r["z"] for r in resumed.search] == [r["z"] for r in rows] and resumed.z == state.z


def test_a_batch_yields_each_points_evaluation_or_error_and_simulates_only_what_is_asked():
    class Stand:
        evaluate_batch = Objective.evaluate_batch

        def __init__(self):
            self.asked = []

        def evaluate(self, z, frames, with_grad=True, min_substeps=1, grid=None):
            self.asked.append((z["e"], frames, with_grad, min_substeps, grid))
            if z["e"] < 0:
                raise UnstableRun("dt exceeds the stable step")
            return SimpleNamespace(loss=z["e"] ** 2)

    stand = Stand()
    points = [{"e": 1.0}, {"e": -1.0}, {"e": 2.0}, {"e": 3.0}]
    results = stand.evaluate_batch(points, 4, min_substeps=3, grid=24)
    assert stand.asked == []  # nothing simulated before it is asked for
    first, failed, third = next(results), next(results), next(results)
    assert first.loss == 1.0 and isinstance(failed, UnstableRun) and third.loss == 4.0  # a failure loses no other
    assert stand.asked == [(1.0, 4, False, 3, 24), (-1.0, 4, False, 3, 24), (2.0, 4, False, 3, 24)]  # not the 4th


def test_the_frame_robust_covariance_is_the_spread_of_refits_under_frame_correlated_errors():
    """A linear model y = A p + e whose errors share one draw per frame: the plain
    Gauss-Newton covariance s^2 (J^T J)^-1 treats the 400 pixels as independent and is far too
    narrow; the frame-robust one matches the spread of the least-squares fits over draws."""
    frames_n, pixels = 20, 20
    gen = torch.Generator().manual_seed(1)
    frames = torch.arange(frames_n).repeat_interleave(pixels)
    # a parameter moves a frame's pixels together, as a modulus moves a frame's flow
    A = torch.randn(frames_n, 2, generator=gen, dtype=torch.float64)[frames]
    A = A + 0.1 * torch.randn(frames_n * pixels, 2, generator=gen, dtype=torch.float64)
    inverse = torch.linalg.inv(A.T @ A)

    def draw():
        per_frame = torch.randn(frames_n, generator=gen, dtype=torch.float64)[frames]
        return per_frame * (1 + A[:, 0].abs()) + 0.01 * torch.randn(len(frames), generator=gen, dtype=torch.float64)

    fits = torch.stack([inverse @ (A.T @ draw()) for _ in range(2000)])
    spread = fits.std(0)
    robust = torch.stack([frame_robust_covariance(A, draw(), frames, inverse).diagonal().sqrt() for _ in range(200)])
    plain = torch.stack([(inverse * float((e := draw()) @ e) / (len(e) - 2)).diagonal().sqrt() for _ in range(200)])
    assert torch.allclose(robust.mean(0), spread, rtol=0.2)
    assert bool((plain.mean(0) < 0.5 * spread).all())  # independent-pixel errors: too narrow


def test_a_fit_shift_is_the_least_squares_move_of_a_linear_model():
    A = torch.tensor([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]], dtype=torch.float64)
    change = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    moved = fit_shift(change, A, torch.linalg.inv(A.T @ A), ("a", "b"))
    expected = torch.linalg.lstsq(A, -change[:, None]).solution.flatten()
    assert [moved["a"], moved["b"]] == pytest.approx(expected.tolist())


@pytest.mark.parametrize(
    "z, sigma, floor, expected",
    [(0.0, 0.1, 0.0, (-RANGE_Z * 0.1, RANGE_Z * 0.1)), (0.0, 0.1, 1.0, (-1.0, 1.0)), (0.9, 0.2, 0.0, (0.9 - RANGE_Z * 0.2, None)),
     (-0.9, 0.2, 0.0, (None, -0.9 + RANGE_Z * 0.2)), (0.0, 5.0, 0.0, (None, None))],
)  # fmt: skip
def test_a_range_is_open_where_it_leaves_the_searched_box(z, sigma, floor, expected):
    low, high = parameter_range(z, sigma, (-1.0, 1.0), floor)
    for got, want in zip((low, high), expected):
        assert got is None if want is None else got == pytest.approx(want)


def test_measured_ends_widen_a_range_and_open_it_only_where_the_box_edge_stays_inside():
    low, high = parameter_range(0.0, 0.1, (-1.0, 1.0), walked=(0.5, None))
    assert low == pytest.approx(-0.5) and high is None
    low, high = parameter_range(0.0, 0.1, (-1.0, 1.0), walked=(0.01, 0.9))  # never narrower
    assert low == pytest.approx(-RANGE_Z * 0.1) and high == pytest.approx(0.9)


LOSS, LIMIT = 2.0, 3.0  # the fit's loss and the tolerance's: a rise of 50 %


def walked(rise, start=0.1, edge=10.0):
    """walk_end on a loss LOSS * (1 + rise(step)), and the steps it ran."""
    half, runs = walk_end(lambda step: LOSS * (1 + rise(step)), start, edge, LIMIT, LOSS)
    return half, [step for step, _ in runs]


def test_a_quadratic_loss_keeps_the_gauss_newton_end():
    """A quadratic rise that reaches the tolerance at the start, or 95 % of it: one run
    confirms it; at 80 % the walk brackets the crossing."""
    half, steps = walked(lambda s: 0.5 * (s / 0.1) ** 2)
    assert half == 0.1 and steps == [0.1]
    half, steps = walked(lambda s: (1 + WALK_REACHED) / 2 * 0.5 * (s / 0.1) ** 2)
    assert half == 0.1 and steps == [0.1]
    half, steps = walked(lambda s: 0.8 * 0.5 * (s / 0.1) ** 2)
    assert steps == pytest.approx([0.1, 0.15, 0.125]) and 0.1 < half < 0.1 / 0.8**0.5  # halved to 25 %


def test_a_flatter_loss_moves_the_end_out_to_where_it_crosses_the_tolerance():
    """A rise linear in the step crossing the tolerance (0.5) at 0.7, from a start of 0.1 (a
    rise of 1/14): the next step is 4x (the secant's 7x, capped), and from 0.4 the secant
    lands on 0.7. A quadratic rise crossing at 0.7: the secant from 0.1 to 0.4 reaches beyond
    it, and halving the bracket until it spans at most a quarter of its inner end, then the
    chord across it, ends the range inside the crossing."""
    half, steps = walked(lambda s: 0.5 * s / 0.7)
    assert steps == pytest.approx([0.1, 0.4, 0.7]) and half == pytest.approx(0.7)
    rise = lambda s: 0.5 * (s / 0.7) ** 2  # noqa: E731
    half, steps = walked(rise)
    beyond = 0.4 + (0.5 - rise(0.4)) / ((rise(0.4) - rise(0.1)) / 0.3)
    assert steps[:3] == pytest.approx([0.1, 0.4, beyond]) and len(steps) <= WALK_RUNS
    inside = max(s for s in steps if rise(s) <= 0.5)
    outside = min(s for s in steps if rise(s) > 0.5)
    assert outside - inside <= WALK_BRACKET * inside < outside - max(s for s in steps[:-1] if rise(s) <= 0.5)
    assert half == pytest.approx(inside + (outside - inside) * (0.5 - rise(inside)) / (rise(outside) - rise(inside)))
    assert 0.6 < half < 0.7


def test_halving_the_bracket_finds_a_crossing_behind_a_wall():
    """A flat rise (0.2 per z unit) up to a wall at 1.5 (the sponge's foam collapsing): the
    step beyond lands far up the wall, where a chord across it would end the range at 1.004;
    halving the bracket three times ends it at 1.47, inside the crossing at 1.54."""
    half, steps = walked(lambda s: 0.2 * s + 100 * max(0.0, s - 1.5) ** 2, start=1.0)
    assert steps == pytest.approx([1.0, 2.5, 1.75, 1.375, 1.5625])
    assert 1.45 < half < 1.54


def test_a_loss_still_inside_after_the_last_run_ends_there_and_one_inside_at_the_edge_is_open():
    half, steps = walked(lambda s: 0.001 * s, edge=1e3)
    assert len(steps) == WALK_RUNS and half == pytest.approx(steps[-1])  # an inner bound
    half, steps = walked(lambda s: 0.01 * s, edge=0.3)
    assert half is None and steps == pytest.approx([0.1, 0.3])


def test_a_steeper_loss_or_a_failed_run_keeps_the_start():
    assert walked(lambda s: 100 * s)[0] == 0.1  # beyond at once: interpolation would narrow it
    half, runs = walk_end(lambda step: None, 0.1, 1.0, LIMIT, LOSS)
    assert half == 0.1 and runs == []
    assert walk_end(lambda step: LOSS, 0.0, 1.0, LIMIT, LOSS) == (0.0, [])  # no width to walk from
    # a run that fails while halving a bracket: the chord across the bracket it had
    values = {1.0: 2.5, 2.0: 400.0}
    half, runs = walk_end(values.get, 1.0, 10.0, LIMIT, LOSS)  # the run at 1.5 fails
    assert [s for s, _ in runs] == [1.0, 2.0] and half == pytest.approx(1.0 + (3.0 - 2.5) / (400 - 2.5))


def test_walks_in_lockstep_end_as_each_alone_and_run_a_round_as_one_batch():
    """Three sides walked together (one confirmed at once, one halving a bracket, one that
    cannot start): each ends as it would alone, and each round asks every unfinished walk's
    next step in one batch, so the first round holds them all."""
    rises = [lambda s: 0.5 * (s / 0.1) ** 2, lambda s: 0.5 * (s / 0.7) ** 2, lambda s: 0.0]
    starts = [0.1, 0.1, 20.0]  # the last beyond its edge: open, no run
    alone = [walk_end(lambda s, r=r: LOSS * (1 + r(s)), a, 10.0, LIMIT, LOSS) for r, a in zip(rises, starts)]
    rounds = []

    def losses_of(asked):
        rounds.append([index for index, _ in asked])
        return [LOSS * (1 + rises[index](step)) for index, step in asked]

    together = walk_in_lockstep([walk_steps(a, 10.0, LIMIT, LOSS) for a in starts], losses_of)
    assert together == alone and alone[2] == (None, [])
    assert rounds[0] == [0, 1] and all(r == [1] for r in rounds[1:]) and len(rounds) == len(alone[1][1])


def test_search_samples_within_the_tolerance_widen_a_range_and_the_extreme_one_opens_it():
    """Samples (z, loss) of a search: those within the tolerance of the best loss stretch the
    range; where the most extreme sample examined is among them, that side is open."""
    search = [{"z": {"a": a, "b": b}, "loss": loss} for a, b, loss in
              [(0.0, -2.0, 1.0), (0.5, -1.0, 1.3), (2.0, 0.0, 1.9), (-1.0, 1.0, 5.0), (3.0, 2.0, 9.0)]] + [
              {"z": {"a": 9.0, "b": 9.0}, "loss": None}]  # fmt: skip
    ranges = {"a": {"low": 9.5, "high": 10.5}, "b": {"low": -0.5, "high": 0.5}, "v": {"low": 0.0, "high": 1.0}}
    values = lambda z: {n: 10**v for n, v in z.items()}  # noqa: E731  (log-scale parameters)
    widen_by_search(ranges, {"a": 1.0, "b": 0.0, "v": 0.5}, search, 1.0, values)
    assert ranges["a"]["low"] == 1.0 and ranges["a"]["high"] == 100.0  # kept: a in 0 .. 2, losses <= 2
    assert ranges["b"]["low"] is None and ranges["b"]["high"] == 0.5  # b's lowest sample (-2) is kept
    assert ranges["v"] == {"low": 0.0, "high": 1.0}  # not searched: as it was
    assert ranges["a"]["search_kept"] == 3


def test_a_coarse_grids_loss_floor_under_every_sample_keeps_the_same_samples():
    """The allowance is a loss difference: a floor the search grid's model error adds to
    every sample (10x the fit's loss in a two-object case) keeps the samples it kept without
    one, where a fraction of the best would keep them all and open both sides."""
    losses = [(0.0, 0.107), (0.2, 0.12), (0.5, 0.2), (-1.0, 0.5), (3.0, 0.9)]
    for floor in (0.0, 1.0):
        search = [{"z": {"a": a}, "loss": floor + loss} for a, loss in losses]
        (low, high), (low_open, high_open), kept = search_extent(search, 0.05)["a"]
        assert (low, high, kept) == (0.0, 0.2, 2) and not (low_open or high_open)


def bowl(bottom: float, depth: float = 1.0, floor: float = 0.01):
    """A 1-D own-calibration loss in z with its minimum ``floor`` at ``bottom``; runs counted."""
    calls = []

    def loss(z):
        calls.append(dict(z))
        return floor + depth * (z["a"] - bottom) ** 2

    return loss, calls


def search_line(loss, f0=None, z0=0.0, max_step=LM_MAX_STEP, g_lm=None, box=None):
    steps = boxed_steps(box or {})
    z = {"a": z0}
    return line_search(
        loss,
        z,
        loss(z) if f0 is None else f0,
        torch.ones(1, 1, dtype=torch.float64),  # J = 1: the loss is r^2 + floor, r = z - bottom
        LM_DAMPING,
        ("a",),
        lambda M, g, at: steps.bounded_step(M, g, at, ("a",)),
        max_step=max_step,
        g_lm=g_lm,
        box=box,
    )


def test_the_line_search_moves_to_a_lower_loss_along_the_direction():
    loss, calls = bowl(0.3)
    found = search_line(loss)
    runs = len(calls) - 1  # f0's own
    assert found["moved"] and found["z"]["a"] == pytest.approx(0.3, abs=0.03)
    assert found["loss"] < 0.01 + 0.03**2 < loss({"a": 0.0})
    # the slope from its difference quotient LINE_STEP wide: (f1 - f0) / 2h = J^T r + h / 2
    assert found["slope"] == [pytest.approx(-0.3 + LINE_STEP / 2)]
    assert found["direction"][0] > 0
    assert runs == len(found["points"]) <= 1 + LINE_MAX_GROWTH + 2  # one probe, the line, two inside


def test_the_line_search_takes_its_slope_from_the_loss_not_from_lms_gradient():
    # LM's J^T r0 says uphill along +z (the estimator's noise); the loss itself falls there
    loss, _ = bowl(0.3)
    found = search_line(loss, g_lm=torch.tensor([1.0], dtype=torch.float64))
    assert found["points"][0]["z"]["a"] == pytest.approx(-LINE_STEP)  # the probe on LM's downhill side
    assert found["moved"] and found["z"]["a"] == pytest.approx(0.3, abs=0.03)


def test_the_line_search_goes_no_farther_than_lms_longest_step():
    loss, calls = bowl(5.0, depth=0.01)
    found = search_line(loss, max_step=0.4)
    assert max(abs(c["a"]) for c in calls) <= 0.4 + 1e-12
    assert found["moved"] and found["z"]["a"] == pytest.approx(0.4)


def test_the_line_search_stays_in_the_box():
    loss, calls = bowl(5.0, depth=0.01)
    found = search_line(loss, box={"a": (-1.0, 0.25)})
    assert max(c["a"] for c in calls) <= 0.25 and found["z"]["a"] == pytest.approx(0.25)


@pytest.mark.parametrize("gain, moves", [(0.5 * LINE_GAIN, False), (2 * LINE_GAIN, True)])
def test_the_line_search_refuses_a_gain_under_its_tolerance(gain, moves):
    # the loss 1 at the bottom, 1 + gain at the start: a fall of the fraction gain / (1 + gain)
    loss, _ = bowl(0.3, depth=gain / 0.09, floor=1.0)
    found = search_line(loss)
    assert found["moved"] is moves
    if moves:
        assert found["loss"] < loss({"a": 0.0}) * (1 - LINE_GAIN)
    else:
        assert found["z"] == {"a": 0.0} and found["loss"] == loss({"a": 0.0})
        assert min(p["loss"] for p in found["points"]) < found["loss"]  # lower, but not by enough


def test_a_failed_probe_leaves_the_line_search_where_it_was():
    found = search_line(lambda z: math.inf, f0=1.0)
    assert not found["moved"] and found["direction"] is None and len(found["points"]) == 1


def test_the_line_search_starts_no_nearer_than_its_difference_width():
    # J^T J sees 20x the curvature the loss has (it holds the estimator's error fixed): the
    # Gauss-Newton step is a twentieth of the way; the first point lies LINE_STEP out, the
    # probe itself in one variable (not run again), and the points grow from there
    loss, calls = bowl(0.6, depth=1 / 20)
    steps = boxed_steps({})
    z0 = {"a": 0.0}
    found = line_search(
        loss,
        z0,
        loss(z0),
        torch.ones(1, 1, dtype=torch.float64),
        LM_DAMPING,
        ("a",),
        lambda M, g, at: steps.bounded_step(M, g, at, ("a",)),
    )
    assert found["direction"][0] == pytest.approx(0.6 / 20, rel=0.1) and found["direction"][0] < LINE_STEP
    line = [c["a"] for c in calls[2:]]  # after f0's run and the probe's
    assert line[:3] == pytest.approx([2 * LINE_STEP, 4 * LINE_STEP, 8 * LINE_STEP])
    assert found["moved"] and found["z"]["a"] == pytest.approx(0.6, abs=0.1)
