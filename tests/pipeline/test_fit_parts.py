"""The optimiser's parts (clflow.pipeline.fit) on their own, with small inputs: no scene, no
simulation, no Optimization; each part is given only the attributes it reads."""

from types import SimpleNamespace

import pytest
import torch

from clflow.pipeline.fit.diagnostics import PROFILE_RISE, flat
from clflow.pipeline.fit.search import Search
from clflow.pipeline.fit.steps import Steps, phase_of, rate_schedule


class BoxedSteps(Steps):
    """Steps with a local box (z units) and nothing else."""

    def __init__(self, box: dict[str, tuple[float, float]]):
        self._local_box = box


M = torch.tensor([[4.0, 0.5], [0.5, 0.1]], dtype=torch.float64)  # b is poorly determined
G = torch.tensor([-2.0, -0.5], dtype=torch.float64)


def test_bounded_step_solves_the_model_when_no_edge_is_in_the_way():
    step = BoxedSteps({}).bounded_step(M, G, {"a": 0.0, "b": 0.0}, ("a", "b"))
    torch.testing.assert_close(M @ step, -G)


def test_bounded_step_holds_a_variable_on_its_edge_and_solves_the_rest_without_it():
    z = {"a": 0.0, "b": 1.0}  # b on its upper edge; the free solution pushes it up
    assert float(BoxedSteps({}).bounded_step(M, G, z, ("a", "b"))[1]) > 0
    step = BoxedSteps({"b": (-1.0, 1.0)}).bounded_step(M, G, z, ("a", "b"))
    assert float(step[1]) == 0.0 and float(step[0]) == pytest.approx(-float(G[0]) / float(M[0, 0]))


def test_the_trust_region_cuts_the_poorly_determined_component_most():
    steps, z = BoxedSteps({}), {"a": 0.0, "b": 0.0}
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


class GridSearch(Search):
    """Search with a fixed box, parameters and counts (what neighbourhoods and refinement read)."""

    def __init__(self, starts: int, refine: int):
        self.cfg = SimpleNamespace(optimize=SimpleNamespace(search=SimpleNamespace(starts=starts, refine=refine)))
        self.params = {"e": None, "nu": None}

    def search_box(self, z0):
        return {"e": (0.0, 4.0), "nu": (0.0, 1.0)}


def test_second_round_regions_are_the_best_distinct_samples_cut_to_the_box():
    rows = [
        {"z": {"e": 1.0, "nu": 0.5}, "loss": 0.1},
        {"z": {"e": 1.1, "nu": 0.5}, "loss": 0.2},  # inside the best one's box: not a centre
        {"z": {"e": 3.9, "nu": 0.9}, "loss": 0.3},
        {"z": {"e": 2.0, "nu": 0.1}, "loss": None},  # a failed sample
    ]
    regions = GridSearch(starts=2, refine=5).neighbourhoods(rows, {"e": 0.0, "nu": 0.0})
    assert [i for i, _ in regions] == [0, 2]
    spacing = 4.0 * len(rows) ** -0.5  # the box's width / samples^(1/parameters)
    assert regions[0][1]["e"] == pytest.approx((1.0 - spacing / 2, 1.0 + spacing / 2))
    assert regions[1][1]["e"][1] == 4.0 and regions[1][1]["nu"][1] == 1.0  # cut to the search box
    points = GridSearch(starts=2, refine=5).refinement_points(regions, {"e": 0.0, "nu": 0.0})
    assert [i for i, _ in points] == [0, 0, 0, 2, 2]  # 5 shared, the first region one more
    for i, z in points:
        assert all(lo <= z[n] <= hi for n, (lo, hi) in dict(regions)[i].items())
