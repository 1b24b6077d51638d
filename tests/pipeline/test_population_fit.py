"""The identification's independent runs as populations (clflow.pipeline.fit.population): in
the GPU plan (forced, copy mode) a batch of the quick demo's points gives each point the loss
of its own evaluation, to the bit, a failing point its own error, and the CPU plan keeps
running them one by one."""

import pytest

from clflow.pipeline.fit import population
from clflow.pipeline.fit.driver import Optimization


@pytest.fixture
def gpu_plan(monkeypatch, copy_mode):
    monkeypatch.setenv("CLFLOW_KERNELS", "gpu")
    monkeypatch.delenv("CLFLOW_P2G", raising=False)


def points_around(problem, count: int) -> list[dict[str, float]]:
    """``count`` points of z: the start's Young's modulus stepped by 2.3 % (z holds its log10)."""
    z0 = problem.initial_state().z
    (name,) = [n for n in z0 if "youngs_modulus" in n]
    return [dict(z0, **{name: z0[name] + 0.01 * k}) for k in range(count)]


def test_a_batch_in_populations_gives_each_points_own_loss_to_the_bit(demo_config, gpu_plan, monkeypatch):
    opt = Optimization(demo_config())
    objective, grid = opt.objective, opt.problem.search_grid
    assert population.populations_pay()
    points = points_around(opt.problem, 4)
    simulated = []
    real = population.run_population
    monkeypatch.setattr(population, "run_population", lambda *a: simulated.append(len(a[1])) or real(*a))
    batch = list(objective.evaluate_batch(points, 3, grid=grid))
    assert sum(simulated) == len(points) and max(simulated) > 1  # populations, not one by one
    for z, result in zip(points, batch):
        alone = objective.evaluate(z, 3, with_grad=False, grid=grid)
        assert result.loss == alone.loss and result.substeps == alone.substeps
        assert all((a == b).all() for a, b in zip(result.flows, alone.flows))


def test_a_point_past_the_substep_limit_fails_alone(demo_config, gpu_plan):
    opt = Optimization(demo_config())
    objective, grid = opt.objective, opt.problem.search_grid
    points = points_around(opt.problem, 3)
    name = next(n for n in points[0] if "youngs_modulus" in n)
    points[1] = dict(points[1], **{name: points[1][name] + 6})  # a million times stiffer: more substeps than allowed
    first, failed, third = objective.evaluate_batch(points, 2, grid=grid)
    assert isinstance(failed, Exception) and "substeps" in str(failed)
    assert first.loss == objective.evaluate(points[0], 2, with_grad=False, grid=grid).loss
    assert third.loss == objective.evaluate(points[2], 2, with_grad=False, grid=grid).loss


def test_the_cpu_plan_runs_the_points_one_by_one(demo_config, monkeypatch):
    monkeypatch.setenv("CLFLOW_KERNELS", "cpu")
    assert not population.populations_pay()
    monkeypatch.setattr(population, "run_population", lambda *a: pytest.fail("a population on the CPU plan"))
    opt = Optimization(demo_config())
    results = list(opt.objective.evaluate_batch(points_around(opt.problem, 2), 2, grid=opt.problem.search_grid))
    assert all(r.loss > 0 for r in results)
