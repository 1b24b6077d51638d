"""Diagnostics of an optimisation's result: identifiability, profiles and the grid check."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Generator

import torch

from clflow.errors import ClflowError, InputError
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.state import Evaluation

log = logging.getLogger(__name__)

# identifiability: a variable is weakly constrained beyond this standard error in z (a factor
# 1.26 of a log-scale parameter), two trade off beyond this correlation
WEAK_STD_Z = 0.1
TRADE_OFF_CORRELATION = 0.95
# ... or when such a step (the others refitted) raises the loss by less than this fraction: the
# standard errors treat pixels as independent noise, but what remains at the optimum is mostly
# model error (the grid, the estimator), which moves the minimum by more than that
MIN_LOSS_RISE = 0.01
# How each check works, and the benchmark cases that set these constants:
# docs/pipeline.md, "Identifiability" (the profile, the grid check, the ranges and their walks).
# a weakly constrained material parameter is moved alone PROFILE_STEP either way in z (a
# decade of a log-scale parameter, cut to its box); it is unresolved over that range when
# neither move changes the loss by PROFILE_RISE of itself
PROFILE_STEP = 1.0
PROFILE_RISE = 0.1
# the grid check reruns the final point on the search grid (without a coarser search grid, on
# one GRID_CHECK_RATIO times coarser) and moves the best fit by the residuals' change: a
# variable whose fit moves more than WEAK_STD_Z is grid-sensitive; a second run on one
# GRID_CHECK_RATIO times finer catches the model error a coarser grid does not show where the
# convergence in the grid is not monotone
GRID_CHECK_RATIO = 1.5
# the reported range: a two-sided 90 % normal range, z +- RANGE_Z * sigma, where sigma^2 adds
# the frame-robust (sandwich) variance, the model grid's own discretisation error (Richardson's
# rule for a first-order method: a grid check's shift times h / |H - h|, h the model grid's
# spacing and H the check's; the larger of the two checks') and the time-step check's shift
# (substeps doubled); at least as wide as the Gauss-Newton profile (the others refitted) where
# the loss rises by the model's own loss tolerance (the relative change those checks make at
# the same point); an end beyond the box the search looked in is open (the data bound only
# that side)
RANGE_LEVEL = 0.9
RANGE_Z = 1.6449
# ... and each end not open is then walked (:func:`walk_steps`), as model error makes the loss
# flatter away from the fit than the quadratic profile says: a forward run at the end along
# the profile's direction (the others refitted to first order), further out while it stays
# within the tolerance, at most WALK_RUNS runs an end, each step out to the secant's crossing,
# WALK_GROWTH times the last at least and at most, then halving the bracket once a run lies
# beyond until it spans at most WALK_BRACKET of its inner end; never narrowing the range. A
# run whose rise is WALK_REACHED of the tolerance's confirms the end where it is: where the
# Gauss-Newton profile sets the end, the first run lands on the tolerance, and one run decides
WALK_RUNS = 6
WALK_BRACKET = 0.25
WALK_GROWTH = (1.5, 4.0)
WALK_REACHED = 0.9


@dataclasses.dataclass(frozen=True)
class RangeWalk:
    """How the ends of the ranges are walked from the fit: per variable its direction in z
    (the others refitted to first order: {other: dz per dz of it}), the loss ``limit`` a
    walk stays within, the fit's ``loss``, the ``substeps`` the runs take at the least, and
    per variable the (below, above) sides the search's samples already opened."""

    directions: dict[str, dict[str, float]]
    limit: float
    loss: float
    substeps: int
    open_sides: dict[str, tuple[bool, bool]]


@dataclasses.dataclass(frozen=True)
class GaussNewtonSpread:
    """How well residuals pin each variable down, in the Gauss-Newton picture (pixels as
    independent noise): ``inverse`` (J^T J)^-1 [n, n], ``covariance`` s^2 (J^T J)^-1 with s^2
    the loss per residual degree of freedom, ``std`` [n] its standard errors (z units:
    decades for log-scale parameters; lower bounds), ``rise`` the fraction of the ``loss``
    that a step of WEAK_STD_Z costs with the other variables refitted."""

    inverse: torch.Tensor
    covariance: torch.Tensor
    std: torch.Tensor
    rise: list[float]
    loss: float

    def weak(self, variables: tuple[str, ...]) -> list[str]:
        """The weakly constrained ``variables`` (named in J's column order): a standard error
        beyond WEAK_STD_Z or a rise under MIN_LOSS_RISE."""
        return [
            n
            for n, sd, r in zip(variables, self.std.tolist(), self.rise)
            if not (sd <= WEAK_STD_Z and r >= MIN_LOSS_RISE)
        ]


def gauss_newton_spread(J: torch.Tensor, residuals: torch.Tensor) -> GaussNewtonSpread:
    """The :class:`GaussNewtonSpread` of ``residuals`` [R] with Jacobian ``J`` [R, n]."""
    count = J.shape[1]
    dof = max(1, residuals.numel() - count)
    curvature = J.T @ J
    ridge = 1e-12 * float(curvature.diagonal().max().clamp(min=1e-300))  # an unconstrained direction: huge
    inverse = torch.linalg.inv(curvature + ridge * torch.eye(count, dtype=curvature.dtype))
    loss = float((residuals**2).sum())
    covariance = inverse * (loss / dof)
    std = covariance.diagonal().clamp(min=0).sqrt()
    rise = (WEAK_STD_Z**2 / inverse.diagonal().clamp(min=1e-300) / max(loss, 1e-300)).tolist()
    return GaussNewtonSpread(inverse, covariance, std, rise, loss)


def frame_robust_covariance(
    J: torch.Tensor, residuals: torch.Tensor, frames: torch.Tensor, inverse: torch.Tensor
) -> torch.Tensor:
    """[P, P] covariance in z of a least-squares fit whose errors are correlated within a
    frame step and independent across steps (the cluster-robust sandwich (J^T J)^-1 M
    (J^T J)^-1, M = sum over steps of g_t g_t^T, g_t = J_t^T r_t centred, times n/(n-1)).
    ``J`` [R, P] and ``residuals`` [R] at the fit, ``frames`` [R] each residual's step,
    ``inverse`` (J^T J)^-1. Where the residuals are model error rather than noise, a step
    whose misfit pulls the parameters its own way widens it: it is how far the estimate
    moves when the frames are weighed differently (a linearised bootstrap over frames)."""
    steps = int(frames.max()) + 1
    g = torch.zeros(steps, J.shape[1], dtype=J.dtype).index_add_(0, frames, J * residuals[:, None])
    g = g - g.mean(0)
    meat = g.T @ g * (steps / max(steps - 1, 1))
    return inverse @ meat @ inverse


def fit_shift(change: torch.Tensor, J: torch.Tensor, inverse: torch.Tensor, variables: tuple[str, ...]) -> dict:
    """Per variable, how far a least-squares fit (Jacobian ``J`` [R, P], ``inverse`` =
    (J^T J)^-1) moves, to first order, when its residuals change by ``change`` [R] (the same
    point run another way, against the same targets): -(J^T J)^-1 J^T change."""
    return dict(zip(variables, (-(inverse @ (J.T @ change))).tolist()))


def parameter_range(
    z: float, sigma: float, box: tuple[float, float], floor: float = 0.0, walked: tuple = (0.0, 0.0)
) -> tuple:
    """(low, high) in z of a parameter at ``z`` with standard deviation ``sigma`` (z units): z
    +- RANGE_Z * sigma, at least +- ``floor`` and at least ``walked`` (below, above: half-widths
    that forward runs measured, None for open); an end beyond ``box`` (lower, upper), where the
    search looked, is None (open: the data only bound the other side)."""
    half = max(RANGE_Z * sigma, floor)
    below, above = (None if w is None else max(half, w) for w in walked)
    low, high = (None if below is None else z - below), (None if above is None else z + above)
    return (None if low is None or low < box[0] else low), (None if high is None or high > box[1] else high)


def walk_steps(start: float, edge: float, limit: float, loss: float) -> Generator[float, float | None, tuple]:
    """One side of a range walked outwards: yields each step (z units out from the fit) to
    run and is sent that run's loss (None where it failed); returns (the half-width in z,
    the (step, loss) runs made). From ``start`` (the half-width so far) outwards while the
    loss stays within ``limit``, each step out to where the secant from
    the last run inside reaches ``limit``, WALK_GROWTH[0] to WALK_GROWTH[1] times the last
    step (a loss that flattens goes out fast); once a run lies beyond, the rest of the
    WALK_RUNS runs halve the bracket until it spans at most WALK_BRACKET of its inner end. The end is the crossing interpolated linearly in the
    last bracket (an inner bound of a convex rise), a run that rose WALK_REACHED of the way
    to ``limit``, or the last run inside; None (open) where the run at ``edge``, the searched
    box's edge, stays inside. Never below ``start``: a loss steeper than the quadratic (the
    first run beyond) keeps the range it had. ``loss``: the loss at the fit. A generator,
    so that the walks of every side and parameter advance together (:func:`walk_in_lockstep`)."""
    inside, beyond, step, runs = (0.0, loss), None, start, []
    if not (0 < start <= edge and math.isfinite(start) and math.isfinite(limit)):  # nothing to walk from
        return (None if start > edge else start), runs
    for _ in range(WALK_RUNS):
        if beyond is not None and beyond[0] - inside[0] <= WALK_BRACKET * inside[0]:
            break
        step = min(step, edge) if beyond is None else (inside[0] + beyond[0]) / 2
        value = yield step
        if value is None or not math.isfinite(value):
            break
        runs.append((step, value))
        if value > limit:
            if step == start:
                return start, runs
            beyond = (step, value)
            continue
        if value - loss >= WALK_REACHED * (limit - loss):
            return step, runs
        if beyond is not None:  # halving: the next step is the bracket's middle
            inside = (step, value)
            continue
        if step >= edge:
            return None, runs
        slope = (value - inside[1]) / (step - inside[0])  # the secant from the last run inside
        inside = (step, value)
        growth = 1 + (limit - value) / max(slope * step, 1e-300)
        step *= min(max(growth, WALK_GROWTH[0]), WALK_GROWTH[1])
    if beyond is None:
        return max(start, inside[0]), runs
    (before, below), (after, above) = inside, beyond
    return max(start, before + (after - before) * (limit - below) / (above - below)), runs


def walk_in_lockstep(walks: list[Generator], losses_of: Callable[[list[tuple[int, float]]], list]) -> list[tuple]:
    """The results of the :func:`walk_steps` generators ``walks``, advanced together: each
    round, every unfinished walk's next step, run by ``losses_of([(walk index, step), ...])``
    (one loss or None per step, in that order) as one batch."""
    results: list = [None] * len(walks)
    pending = []
    for index, walk in enumerate(walks):
        try:
            pending.append((index, next(walk)))
        except StopIteration as end:
            results[index] = end.value
    while pending:
        asked, pending = pending, []
        for (index, _), value in zip(asked, losses_of(asked)):
            try:
                pending.append((index, walks[index].send(value)))
            except StopIteration as end:
                results[index] = end.value
    return results


def walk_end(loss_at: Callable[[float], float | None], start: float, edge: float, limit: float, loss: float) -> tuple:
    """:func:`walk_steps` alone, each step's loss from ``loss_at(step)``."""
    return walk_in_lockstep([walk_steps(start, edge, limit, loss)], lambda asked: [loss_at(s) for _, s in asked])[0]


def widen_by_search(ranges: dict[str, dict], z: dict[str, float], search: list[dict], allowance: float, values) -> None:
    """Widen each range (Diagnostics.ranges, in place) to the search samples whose loss is
    within ``allowance`` of the search's best (state.search rows: z, loss): the non-local
    profile the search's own runs give for free (quick playdoh's E reaches its truth only
    through the samples kept: 4.6e5 to 1e8 Pa, where the final point's curvature alone would
    allow 0.1 decade). A side reached by the search's most extreme sample in that
    direction is open: the data do not bound it. ``allowance``: a loss difference, the
    model's loss tolerance times the fit's own loss (:func:`search_extent`). ``values(z)``:
    SI values of a point."""
    extent = search_extent(search, allowance)
    for name, entry in ranges.items():
        if name not in extent:
            continue
        (low, high), (low_open, high_open), kept = extent[name]
        if entry["low"] is not None and low < z[name]:
            entry["low"] = None if low_open else min(entry["low"], values({**z, name: low})[name])
        if entry["high"] is not None and high > z[name]:
            entry["high"] = None if high_open else max(entry["high"], values({**z, name: high})[name])
        entry["search_kept"] = kept


def search_extent(search: list[dict], allowance: float) -> dict[str, tuple]:
    """Per searched variable ((lowest, highest) z of the search samples whose loss exceeds the
    best by at most ``allowance``, (whether that lowest is the lowest sample run, whether that
    highest is the highest), how many samples that is); {} without samples.

    ``allowance`` is a loss difference, not a fraction of the search's best: the search
    ranks its samples on its own, usually coarser, grid, whose model error puts a floor
    under every sample's loss (10x the fit's in a two-object case: 1.07 against 0.107), and a
    fraction of that floor would keep samples the main grid tells apart."""
    rows = [r for r in search if r.get("loss") is not None]
    if not rows:
        return {}
    best = min(r["loss"] for r in rows)
    kept = [r for r in rows if r["loss"] <= best + allowance]
    out = {}
    for name in rows[0]["z"]:
        seen, near = [r["z"][name] for r in rows], [r["z"][name] for r in kept]
        out[name] = (min(near), max(near)), (min(near) <= min(seen), max(near) >= max(seen)), len(kept)
    return out


def flat(profile_row: dict) -> bool:
    """Whether a :meth:`Optimization.profile` row shows a loss that, moved either way, changed
    by at most PROFILE_RISE of itself (a fall is no flatter than a rise: the point is then
    not a minimum along that parameter)."""
    ratios = profile_row["loss_ratio"]
    return len(ratios) > 1 and all(r is not None and abs(r - 1) <= PROFILE_RISE for r in ratios)


class Diagnostics:
    """How well the guidance video pins down the result of an
    :class:`~clflow.pipeline.fit.objective.Objective`: identifiability, ranges, profiles,
    and the grid and time-step checks."""

    def __init__(self, objective: Objective):
        self.objective = objective
        self.problem = objective.problem

    def identifiability(self, z: dict[str, float], min_substeps: int, search: list[dict] | None = None) -> dict:
        """How well the video pins down each variable at z: from the residuals' Jacobian J
        (one forward run per variable), the Gauss-Newton covariance s^2 (J^T J)^-1 with s^2
        the loss per residual degree of freedom. Its standard errors (z units: decades for
        log-scale parameters) treat pixels as independent, so they are lower bounds; the
        correlations show which parameters trade off. ``loss_rise``: the fraction of the loss
        that a step of WEAK_STD_Z costs with the others refitted; a variable is weakly
        constrained when its standard error exceeds WEAK_STD_Z or that rise is below
        MIN_LOSS_RISE. Each weakly constrained material parameter is then profiled
        (:meth:`profile`, two forward runs): ``unresolved`` lists those whose loss is
        :func:`flat` over the range. ``grid_checks``: the final point on a coarser and a finer
        grid (:meth:`grid_checks`); ``grid_shift_z``: how far each variable's best fit moves
        on the coarser one (the finer one where only it ran), ``grid_sensitive`` those moved
        beyond WEAK_STD_Z, whose value the discretisation sets as much as the video."""
        variables = self.problem.main_variables
        base, J = self.objective.jacobian(z, self.problem.frames, min_substeps, variables, self.problem.model_grid)
        residuals = self.objective.residuals(base.flows, base.more_flows)
        spread = gauss_newton_spread(J, residuals)
        inverse, std, rise, loss = spread.inverse, spread.std, spread.rise, spread.loss
        correlation = spread.covariance / torch.outer(std, std).clamp(min=1e-300)
        weak = spread.weak(variables)
        pairs = [
            [a, b, float(correlation[i, j])]
            for i, a in enumerate(variables)
            for j, b in enumerate(variables)
            if i < j and abs(float(correlation[i, j])) > TRADE_OFF_CORRELATION
        ]
        profile = self.profile(z, base.substeps, weak, loss)
        checks = self.grid_checks(z, base, J, inverse, variables)
        check_substeps, dt_shift, dt_change = self.substep_shift(z, base, J, inverse, variables)
        robust = frame_robust_covariance(J, residuals, self.objective.residual_frames(len(base.flows)), inverse)
        unresolved = [n for n, row in profile.items() if flat(row)]
        # the grid's error by Richardson, the larger of the two checks' (two estimates of one
        # error); the time step's, halved, once its own
        grid_error = {n: max(c["richardson"] * abs(c["shift_z"].get(n, 0.0)) for c in checks) for n in variables}
        discretisation = {n: math.hypot(grid_error[n], dt_shift.get(n, 0.0)) for n in variables}
        tolerance = math.hypot(max(c["richardson"] * c["loss_change"] for c in checks), dt_change)
        # where the loss, the others refitted, rises by under that tolerance (Gauss-Newton profile)
        profile_z = [WEAK_STD_Z * math.sqrt(tolerance / max(r, 1e-300)) for r in rise]
        frame_std = robust.diagonal().clamp(min=0).sqrt().tolist()
        # each variable's profile direction: a unit move of it, the others refitted to first order
        directions = {
            n: dict(zip(variables, (inverse[:, i] / inverse[i, i]).tolist())) for i, n in enumerate(variables)
        }
        # the search's samples within the tolerance of the fit's own loss (base.loss: flow.loss,
        # as the samples'; the model grid's) open a side where its most extreme one lies: not walked
        allowance = tolerance * base.loss
        search_open = {
            n: (low_open and low < z[n], high_open and high > z[n])
            for n, ((low, high), (low_open, high_open), _) in search_extent(search or [], allowance).items()
        }
        walk = RangeWalk(
            directions, limit=loss * (1 + tolerance), loss=loss, substeps=base.substeps, open_sides=search_open
        )
        ranges = self.ranges(z, variables, frame_std, discretisation, profile_z, unresolved, walk)
        widen_by_search(ranges, z, search or [], allowance, self.problem.values)
        return {
            "ranges": ranges,
            "loss_tolerance": tolerance,
            "std_z": dict(zip(variables, std.tolist())),
            "loss_rise": dict(zip(variables, rise)),
            "correlation": {a: dict(zip(variables, row)) for a, row in zip(variables, correlation.tolist())},
            "weakly_constrained": weak,
            "trade_offs": pairs,
            "profile": profile,
            "profile_rise": PROFILE_RISE,
            "unresolved": unresolved,
            "grids": [checks[0]["nodes"], self.problem.model_grid],
            "grid_shift_z": checks[0]["shift_z"],
            "grid_sensitive": [n for n, moved in checks[0]["shift_z"].items() if abs(moved) > WEAK_STD_Z],
            "grid_checks": checks,
            "substep_check": check_substeps,
            "substep_shift_z": dt_shift,
        }

    def ranges(
        self,
        z: dict[str, float],
        variables: tuple[str, ...],
        frame_std: list[float],
        discretisation: dict[str, float],
        profile_z: list[float],
        unresolved: list[str],
        walk: RangeWalk,
    ) -> dict[str, dict]:
        """Per variable its RANGE_LEVEL range: ``low`` and ``high`` (SI; None where open),
        ``sigma_z`` and its parts (``frames_z``: the frame-robust standard deviation;
        ``grid_z``: the model grid's discretisation error from the grid check, 0 where it
        failed; ``profile_z``: the half-width where the loss, the others refitted, rises by
        the model's loss tolerance). The range is the widest of RANGE_Z sigma, the profile's
        and, for a parameter whose profile is flat (``unresolved``), PROFILE_STEP, either way;
        each end not open is then walked (:meth:`walks` by ``walk``; ``walked_z``: the half-widths below
        and above, None where open; ``walk_loss_ratio``: below and above, [step in z, loss
        over the fit's] of each run).
        Open ends lie beyond the local phase's box (else the parameter's typical range;
        velocities: none)."""
        sigmas = [
            (frames_z**2 + discretisation.get(name, 0.0) ** 2) ** 0.5 for name, frames_z in zip(variables, frame_std)
        ]
        floors = [
            max(half_profile, PROFILE_STEP if name in unresolved else 0.0)
            for name, half_profile in zip(variables, profile_z)
        ]
        starts = {name: max(RANGE_Z * sigma, floor) for name, sigma, floor in zip(variables, sigmas, floors)}
        walks = self.walks(z, starts, walk)
        out = {}
        for name, frames_z, half_profile, sigma, floor in zip(variables, frame_std, profile_z, sigmas, floors):
            walked, ratios = walks[name]
            low, high = parameter_range(z[name], sigma, self.problem.box_of(name, z), floor, walked)
            out[name] = {
                "value": self.problem.values(z)[name],
                "low": None if low is None else self.problem.values({**z, name: low})[name],
                "high": None if high is None else self.problem.values({**z, name: high})[name],
                "level": RANGE_LEVEL,
                "sigma_z": sigma,
                "frames_z": frames_z,
                "grid_z": discretisation.get(name, 0.0),
                "profile_z": half_profile,
                "walked_z": list(walked),
                "walk_loss_ratio": ratios,
            }
        return out

    def walks(self, z: dict[str, float], starts: dict[str, float], walk: RangeWalk) -> dict[str, tuple[tuple, list]]:
        """Per variable of ``starts`` ((below, above) half-widths in z of its range that
        forward runs measured, the runs' loss ratios [[step, ratio], ...] per side): a
        :func:`walk_steps` each side from ``starts[name]`` along ``walk.directions[name]``
        (the others refitted to first order, each kept in its own box) while the loss stays
        within ``walk.limit``. A side whose start already leaves the box, or that
        ``walk.open_sides`` opens, is not walked (it is open). Every side walks in lockstep:
        a round's runs are one batch (Objective.evaluate_batch: a population where the
        kernel plan gathers)."""
        directions, limit, loss, substeps = walk.directions, walk.limit, walk.loss, walk.substeps
        open_sides = walk.open_sides
        sides, walks = [], []
        for name, start in starts.items():
            box, opened = self.problem.box_of(name, z), open_sides.get(name, (False, False))
            for sign, edge, is_open in ((-1, z[name] - box[0], opened[0]), (1, box[1] - z[name], opened[1])):
                if not (start > edge or is_open):
                    sides.append((name, sign))
                    walks.append(walk_steps(start, edge, limit, loss))

        def moved(side: int, step: float) -> dict[str, float]:
            name, sign = sides[side]
            point = dict(z)
            for other, dz in directions[name].items():
                lo, hi = self.problem.box_of(other, z)
                point[other] = min(max(z[other] + sign * step * dz, lo), hi)
            return point

        def losses_of(asked: list[tuple[int, float]]) -> list[float | None]:
            points = [moved(side, step) for side, step in asked]
            runs = self.objective.evaluate_batch(points, self.problem.frames, min_substeps=substeps)
            losses = []
            for (side, _), point, run in zip(asked, points, runs):
                if isinstance(run, Exception):
                    name = sides[side][0]
                    log.info("the range of %s: the run at %s failed: %s", name, self.problem.values(point)[name], run)
                    losses.append(None)
                else:
                    losses.append(float((self.objective.residuals(run.flows, run.more_flows) ** 2).sum()))
            return losses

        ended = dict(zip(sides, walk_in_lockstep(walks, losses_of)))
        out = {}
        for name in starts:
            halves, ratios = [], []
            for sign in (-1, 1):
                half, runs = ended.get((name, sign), (None, []))
                halves.append(half)
                ratios.append([[step, value / max(loss, 1e-300)] for step, value in runs])
            out[name] = (tuple(halves), ratios)
        return out

    def grid_checks(
        self, z: dict[str, float], base: Evaluation, J: torch.Tensor, inverse: torch.Tensor, variables: tuple[str, ...]
    ) -> list[dict]:
        """The final point ``base`` (residual Jacobian ``J`` [R, P], ``inverse`` = (J^T J)^-1)
        run again, forward only, on a coarser grid (the search grid, or one GRID_CHECK_RATIO
        times coarser without a coarser search grid) and on one GRID_CHECK_RATIO times finer.
        Per check: ``nodes``; ``ran``, False where the run failed; ``shift_z``, per variable
        the move of the best fit in z units from the model grid to that grid (to first order
        -(J^T J)^-1 J^T (r_check - r_model), both against the same targets; empty where the
        run failed); ``loss_change``, the
        loss's relative change (0 where it failed); ``richardson``, the factor h / |H - h|
        (h the model grid's spacing, H the check's) that turns both into the model grid's own
        error for a first-order method: 2 for a 1.5x coarser check, 3 for a 1.5x finer one.
        Where the coarser grid's thicker walls leave the object no room in the domain, the
        finer check is the only one. The coarser check comes first."""
        coarse = self.problem.search_grid
        if coarse >= self.problem.model_grid:
            coarse = round((self.problem.model_grid - 1) / GRID_CHECK_RATIO) + 1
        finer = round((self.problem.model_grid - 1) * GRID_CHECK_RATIO) + 1
        try:
            self.problem.prepared_on(coarse)
            grids = [coarse, finer]
        except InputError:
            log.info(
                "the grid check takes only %d nodes: on %d the thicker walls leave the object no room", finer, coarse
            )
            grids = [finer]
        checks = []
        for nodes in grids:
            what = f"the grid check at {nodes} nodes"
            shift, change = self.rerun_shift(z, base, J, inverse, variables, what, grid=nodes)
            richardson = 1 / max(abs((self.problem.model_grid - 1) / (nodes - 1) - 1), 1e-6)
            checks.append(
                {"nodes": nodes, "ran": bool(shift), "shift_z": shift, "loss_change": change, "richardson": richardson}
            )
        return checks

    def substep_shift(
        self, z: dict[str, float], base: Evaluation, J: torch.Tensor, inverse: torch.Tensor, variables: tuple[str, ...]
    ) -> tuple[int, dict[str, float], float]:
        """(the substeps per frame of the check, per variable the move of the best fit in z
        units when the final point ``base`` runs at twice its substeps, the loss's relative
        change): the time step's pull on each estimate, as :meth:`grid_checks` is the grid's (quick playdoh's loss at its
        truth: 0.0057 at 40 substeps per frame, 0.028 at 254). Empty where the run fails."""
        substeps = 2 * base.substeps
        what = f"the time-step check at {substeps} substeps per frame"
        shift, change = self.rerun_shift(
            z, base, J, inverse, variables, what, min_substeps=substeps, grid=self.problem.model_grid
        )
        return substeps, shift, change

    def rerun_shift(
        self,
        z: dict[str, float],
        base: Evaluation,
        J: torch.Tensor,
        inverse: torch.Tensor,
        variables: tuple[str, ...],
        what: str,
        **how,
    ) -> tuple[dict[str, float], float]:
        """The final point ``base`` run again, forward only, another way (``how``: evaluate's
        grid or min_substeps): (the fit's move per variable, :func:`fit_shift`; the loss's
        relative change |L_new / L - 1|). ({}, 0.0) where that run fails."""
        try:
            run = self.objective.evaluate(z, self.problem.frames, with_grad=False, **how)
        except (FloatingPointError, MemoryError, ClflowError) as exc:
            log.warning("%s failed (%s): the ranges leave its error out", what, exc)
            return {}, 0.0
        before, after = (
            self.objective.residuals(base.flows, base.more_flows),
            self.objective.residuals(run.flows, run.more_flows),
        )
        loss_change = abs(float((after**2).sum()) / max(float((before**2).sum()), 1e-300) - 1)
        return fit_shift(after - before, J, inverse, variables), loss_change

    def profile(self, z: dict[str, float], min_substeps: int, names: list[str], loss: float) -> dict:
        """Per material parameter in ``names``: ``values`` (SI) PROFILE_STEP below z, at z and
        PROFILE_STEP above in z units, cut to the local phase's box (else the parameter's
        typical range, widened to hold z; a side on its edge is left out), and ``loss_ratio``,
        the loss there with the others held over ``loss``, the loss at z (None where the run
        failed)."""
        out = {}
        for name in (n for n in names if n in self.problem.params):
            lo, hi = self.problem.box_of(name, z)
            row: dict[str, list] = {"values": [], "loss_ratio": []}
            targets = sorted({max(lo, z[name] - PROFILE_STEP), z[name], min(hi, z[name] + PROFILE_STEP)})
            sides = [{**z, name: target} for target in targets if target != z[name]]
            runs = iter(self.objective.evaluate_batch(sides, self.problem.frames, min_substeps=min_substeps))
            for target in targets:
                moved, ratio = {**z, name: target}, 1.0
                if target != z[name]:
                    ev = next(runs)
                    if isinstance(ev, Exception):
                        log.info("profile of %s at %s failed: %s", name, self.problem.values(moved)[name], ev)
                        ratio = None
                    else:
                        residuals = self.objective.residuals(ev.flows, ev.more_flows)
                        ratio = float((residuals**2).sum()) / max(loss, 1e-300)
                row["values"].append(self.problem.values(moved)[name])
                row["loss_ratio"].append(ratio)
            out[name] = row
        return out
