"""Diagnostics of an optimisation's result: identifiability, profiles and the grid check."""

from __future__ import annotations

import logging

import torch

from clflow.errors import ClflowError, InputError
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
# a weakly constrained material parameter is moved alone PROFILE_STEP either way in z (a
# decade of a log-scale parameter, cut to its box); it is unresolved over that range when
# neither move changes the loss by PROFILE_RISE of itself (the cream's viscosity: under 1 %
# from 1 to 10 Pa s)
PROFILE_STEP = 1.0
PROFILE_RISE = 0.1
# the grid check reruns the final point on the search grid (without a coarser search grid, on
# one GRID_CHECK_RATIO times coarser) and moves the best fit by the residuals' change: a
# variable whose fit moves more than WEAK_STD_Z is grid-sensitive (the full droplet's bulk
# modulus: 0.42 decades from 51 to 76 nodes, where it ended at 0.35 of its truth; the bird's
# E: 0.001 decades, RE 0.05; docs/history/benchmarks-2026-11.md, "The bulk modulus sits below the model error")
GRID_CHECK_RATIO = 1.5


def flat(profile_row: dict) -> bool:
    """Whether a :meth:`Optimization.profile` row shows a loss that, moved either way, changed
    by at most PROFILE_RISE of itself (a fall is no flatter than a rise: the point is then
    not a minimum along that parameter)."""
    ratios = profile_row["loss_ratio"]
    return len(ratios) > 1 and all(r is not None and abs(r - 1) <= PROFILE_RISE for r in ratios)


class Diagnostics:
    """Which digits of a result to believe: standard errors and trade-offs from the residuals'
    Jacobian, profiles of weakly constrained parameters, the grid check (needs evaluate,
    jacobian, residuals, local_box)."""

    def identifiability(self, z: dict[str, float], min_substeps: int) -> dict:
        """How well the video pins down each variable at z: from the residuals' Jacobian J
        (one forward run per variable), the Gauss-Newton covariance s^2 (J^T J)^-1 with s^2
        the loss per residual degree of freedom. Its standard errors (z units: decades for
        log-scale parameters) treat pixels as independent, so they are lower bounds; the
        correlations show which parameters trade off. ``loss_rise``: the fraction of the loss
        that a step of WEAK_STD_Z costs with the others refitted; a variable is weakly
        constrained when its standard error exceeds WEAK_STD_Z or that rise is below
        MIN_LOSS_RISE. Each weakly constrained material parameter is then profiled
        (:meth:`profile`, two forward runs): ``unresolved`` lists those whose loss is
        :func:`flat` over the range. ``grid_shift_z``: how far each variable's best fit moves
        on a coarser grid (:meth:`grid_shift`); ``grid_sensitive`` those moved beyond
        WEAK_STD_Z, whose value the discretisation sets as much as the video."""
        variables = self.main_variables
        base, J = self.jacobian(z, self.frames, min_substeps, variables, self.model_grid)
        residuals, count = self.residuals(base.flows, base.more_flows), len(variables)
        dof = max(1, residuals.numel() - count)
        curvature = J.T @ J
        ridge = 1e-12 * float(curvature.diagonal().max().clamp(min=1e-300))  # an unconstrained direction: huge
        inverse = torch.linalg.inv(curvature + ridge * torch.eye(count, dtype=curvature.dtype))
        loss = float((residuals**2).sum())
        covariance = inverse * (loss / dof)
        std = covariance.diagonal().clamp(min=0).sqrt()
        correlation = covariance / torch.outer(std, std).clamp(min=1e-300)
        # the loss a step of WEAK_STD_Z costs, the other variables refitted, as a fraction of the loss
        rise = (WEAK_STD_Z**2 / inverse.diagonal().clamp(min=1e-300) / max(loss, 1e-300)).tolist()
        weak = [n for n, sd, r in zip(variables, std.tolist(), rise) if not (sd <= WEAK_STD_Z and r >= MIN_LOSS_RISE)]
        pairs = [
            [a, b, float(correlation[i, j])]
            for i, a in enumerate(variables)
            for j, b in enumerate(variables)
            if i < j and abs(float(correlation[i, j])) > TRADE_OFF_CORRELATION
        ]
        profile = self.profile(z, base.substeps, weak, loss)
        coarse_grid, shift = self.grid_shift(z, base, J, inverse, variables)
        return {
            "std_z": dict(zip(variables, std.tolist())),
            "loss_rise": dict(zip(variables, rise)),
            "correlation": {a: dict(zip(variables, row)) for a, row in zip(variables, correlation.tolist())},
            "weakly_constrained": weak,
            "trade_offs": pairs,
            "profile": profile,
            "profile_rise": PROFILE_RISE,
            "unresolved": [n for n, row in profile.items() if flat(row)],
            "grids": [coarse_grid, self.model_grid],
            "grid_shift_z": shift,
            "grid_sensitive": [n for n, moved in shift.items() if abs(moved) > WEAK_STD_Z],
        }

    def grid_shift(
        self, z: dict[str, float], base: Evaluation, J: torch.Tensor, inverse: torch.Tensor, variables: tuple[str, ...]
    ) -> tuple[int, dict[str, float]]:
        """(the coarser grid's nodes, per variable the move of the best fit in z units from
        the model grid to that grid): the final point ``base`` (residual Jacobian ``J``
        [R, P], ``inverse`` = (J^T J)^-1) run again, forward only, on the search grid, or one
        GRID_CHECK_RATIO times coarser without a coarser search grid; to first order the fit
        moves by -(J^T J)^-1 J^T (r_coarse - r_model), both against the same targets. The
        discretisation's pull on each estimate at the scale of the grid refinement: the
        model grid's own bias is of that order too (its sign and size depend on how fast the
        estimate converges with the grid). Where the coarser grid's thicker walls leave the
        object no room in the domain, a GRID_CHECK_RATIO times finer grid instead. Empty
        where the run fails."""
        coarse = self.search_grid
        if coarse >= self.model_grid:
            coarse = round((self.model_grid - 1) / GRID_CHECK_RATIO) + 1
        finer = round((self.model_grid - 1) * GRID_CHECK_RATIO) + 1
        try:
            self.prepared_on(coarse)
        except InputError:
            log.info("the grid check takes %d nodes: on %d the thicker walls leave the object no room", finer, coarse)
            coarse = finer
        try:
            run = self.evaluate(z, self.frames, with_grad=False, grid=coarse)
        except (FloatingPointError, ClflowError) as exc:
            log.info("the grid check at %d nodes failed: %s", coarse, exc)
            return coarse, {}
        change = self.residuals(run.flows, run.more_flows) - self.residuals(base.flows, base.more_flows)
        moved = -(inverse @ (J.T @ change))
        return coarse, dict(zip(variables, moved.tolist()))

    def profile(self, z: dict[str, float], min_substeps: int, names: list[str], loss: float) -> dict:
        """Per material parameter in ``names``: ``values`` (SI) PROFILE_STEP below z, at z and
        PROFILE_STEP above in z units, cut to the local phase's box (else the parameter's
        typical range, widened to hold z; a side on its edge is left out), and ``loss_ratio``,
        the loss there with the others held over ``loss``, the loss at z (None where the run
        failed)."""
        out = {}
        for name in (n for n in names if n in self.params):
            lo, hi = self.local_box().get(name) or self.typical_box(name)
            lo, hi = min(lo, z[name]), max(hi, z[name])
            row: dict[str, list] = {"values": [], "loss_ratio": []}
            for target in sorted({max(lo, z[name] - PROFILE_STEP), z[name], min(hi, z[name] + PROFILE_STEP)}):
                moved, ratio = {**z, name: target}, 1.0
                if target != z[name]:
                    try:
                        ev = self.evaluate(moved, self.frames, with_grad=False, min_substeps=min_substeps)
                        ratio = float((self.residuals(ev.flows, ev.more_flows) ** 2).sum()) / max(loss, 1e-300)
                    except (FloatingPointError, ClflowError) as exc:
                        log.info("profile of %s at %s failed: %s", name, self.values(moved)[name], exc)
                        ratio = None
                row["values"].append(self.values(moved)[name])
                row["loss_ratio"].append(ratio)
            out[name] = row
        return out

    def typical_box(self, name: str) -> tuple[float, float]:
        """(lower, upper) in z of material parameter ``name``'s typical range."""
        p = self.params[name]
        lo, hi = (float(p.encode(v)) for v in p.param.typical) if p.param.scale != "linear" else p.param.typical
        return lo, hi
