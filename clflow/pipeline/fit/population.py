"""Independent forward runs of an identification (a search's samples, the Levenberg-Marquardt
columns, a profile's sides, a round of the range walks, the search starts' scores on the main
grid) simulated together as populations (clflow.mpm.population). The grid and time-step checks run on other grids and step counts
than the fit, so each is a simulation of its own.

Points of the same substep count and time scale (frame step), up to POPULATION at a time,
become the members of one population: one simulator whose launches advance them all. The
members keep their own substep count (points are grouped by it rather than run at the
stiffest one's), so each is
its own run: on the gather P2G path (the GPU plan) to the bit, as its losses then are. A
population that fails or ends unstable (NaN, a CFL breach, particles clamped) is run again
point by point, so that each point fails or not on its own, as it would alone.

Populations pay where the host's launches are what the device waits for: the GPU plan. On
the CPU plan the host is not the limit, and the private P2G copies' boxes would span every
member between a particle chunk's first and last: the points run one by one there.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from clflow.errors import ClflowError
from clflow.pipeline.simulation import build_simulator, particle_velocities, run

POPULATION = 32  # members at most in one population (a search's samples a round)


@dataclass
class RunPoint:
    """One point's run, built and not yet run: z as tensors (``grads_of`` require grad), the
    grid it runs on and the scene prepared there, the objects' values, the simulator, the
    inputs of clflow.pipeline.simulation.run (SI values by parameter; the initial velocity
    or None), and the simulated seconds per video second its simulator was built with."""

    zt: dict[str, torch.Tensor]
    grads_of: tuple[str, ...]
    grid: int
    prepared: object
    objects: list
    sim: object
    run_values: dict[str, torch.Tensor]
    velocity: torch.Tensor | None
    time_scale: float


def run_point(point: RunPoint, frames: int, reader=None):
    """The differentiable run of ``point`` (Frames; with a ``reader`` of its frames on the
    device, (Frames, the reader's tensors)); a step or run that is unstable is for the caller
    to judge (Objective._evaluation), so its warnings are not shown."""
    from clflow.mpm import StabilityWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StabilityWarning)
        return run(point.sim, frames, point.run_values, point.velocity, reader=reader)


def populations_pay() -> bool:
    """Whether independent runs are simulated as populations: where the device's kernel plan
    gathers P2G (the GPU plan; see the module's docstring)."""
    from clflow.runtime import get_device
    from clflow.runtime.plan import kernel_plan

    return kernel_plan(get_device()).p2g == "gather"


def evaluate_in_populations(objective, points: list[dict[str, float]], frames: int, min_substeps: list[int], grid: int):
    """Objective.evaluate_batch's results for ``points`` (each run at ``min_substeps`` of its
    own at least), in their order (an Evaluation or the error of each), the points simulated
    in populations of equal substep counts and time scales."""
    results: list = [None] * len(points)
    built: dict[int, RunPoint] = {}
    for i, (z, least) in enumerate(zip(points, min_substeps)):
        try:
            built[i] = objective._point(z, grid, least)
        except (FloatingPointError, ClflowError) as exc:  # a substep limit: this point alone
            results[i] = exc
    groups: dict[tuple[int, float], list[int]] = {}
    for i, point in built.items():
        groups.setdefault((point.sim.substeps, point.time_scale), []).append(i)
    for indices in groups.values():
        for start in range(0, len(indices), POPULATION):
            members = indices[start : start + POPULATION]
            runs = (
                run_population(objective.problem.cfg, [built[i] for i in members], frames) if len(members) > 1 else None
            )
            for j, i in enumerate(members):
                try:
                    traj = runs[j] if runs is not None else run_point(built[i], frames)
                    results[i] = objective._evaluation(built[i], traj, frames)
                except (FloatingPointError, ClflowError) as exc:
                    results[i] = exc
    return results


def run_population(cfg, points: list[RunPoint], frames: int) -> list | None:
    """Each point's Frames from one population run of ``points`` (of scene config ``cfg``, on
    the same grid, of one substep count and time scale), or None when the population fails or ends unstable
    (then they run one by one)."""
    from clflow.mpm.autograd import simulate

    first = points[0]
    try:
        with warnings.catch_warnings():  # a failure here is judged point by point, again
            warnings.simplefilter("ignore")
            population = build_simulator(
                cfg,
                first.prepared.setup,
                [p.objects for p in points],
                min_substeps=first.sim.substeps,
                max_substeps=cfg.simulation.max_substeps,
                time_scale=first.time_scale,
            )
            if population.substeps != first.sim.substeps:
                return None
            values = member_values([p.run_values for p in points], first.sim.n)
            velocities = torch.cat([member_velocity(p) for p in points])
            params = {name: value for name, value in values.items() if name != "density"}
            out = simulate(
                population, frames, params=params or None, density=values.get("density"), velocities=velocities
            )
    except (FloatingPointError, ClflowError):
        return None
    if out.unstable:
        return None
    member = lambda m: out.replace(out.x[:, m], out.v[:, m], out.F[:, m])  # noqa: E731
    return [member(m) for m in range(len(points))]


def member_values(values: list[dict[str, torch.Tensor]], n: int) -> dict[str, torch.Tensor]:
    """The members' run values by parameter as one population's: [K] where each member gives
    one value, else [K n] (each member's per-particle values, n particles a member)."""
    out = {}
    for name in values[0]:
        column = [v[name] for v in values]
        if all(t.dim() == 0 for t in column):
            out[name] = torch.stack(column)
        else:
            out[name] = torch.cat([t.expand(n) if t.dim() == 0 else t for t in column])
    return out


def member_velocity(point: RunPoint) -> torch.Tensor:
    """[n, 3] the initial velocity (m/s) ``point``'s run starts from."""
    if point.velocity is None:
        return point.sim.state.v.clone()
    return particle_velocities(point.sim, point.velocity)
