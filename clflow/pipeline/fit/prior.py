"""A prior from the material query for what the guidance video leaves undetermined
(``optimize.prior: knowledge``).

A parameter the identifiability check flags weakly constrained or unresolved goes wherever
the video's artefacts (blur, a lossy codec, the camera's shake left over) push it, and the
parameters it trades off with follow it (a plasticine's E follows its Poisson's ratio). The
prior is what the material knowledge base says of the object: the query's answer and the
range of the entry it matched, else the median of its material type's entries and the union
of their ranges (what any object of that type may have). After the fit:

- an unresolved parameter (its loss flat over a decade either way: the video has no say)
  takes the prior's value;
- a weakly constrained one the video left outside the prior's range moves to that range's
  nearest point (a value inside it stays);

each within the parameter's own 90 % range (at its end where the prior lies beyond), every
other variable refitted to first order (the residuals' Jacobian at the fit). The move is
kept only where a forward run confirms that its loss stays within the model's loss
tolerance of the fit's (the ranges' own criterion), else half of it, and so on
(MOVE_FRACTIONS). It is the MAP estimate under that prior with a weight too small to move
anything the video determines: the prior decides only among the points the video cannot
tell apart. The ranges stay the video's alone, so they hold the truth as often as without
the prior; ``metrics.json``'s ``prior`` says per parameter who decided it.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import torch

from clflow.errors import ClflowError, InputError
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.state import Evaluation
from clflow.scene.config import TIME_SCALE, VELOCITY, SceneConfig, split_parameter

log = logging.getLogger(__name__)

# the prior's move is tried whole, then at these fractions, until a run's loss stays within
# the model's loss tolerance of the fit's; none passing: no move
MOVE_FRACTIONS = (1.0, 0.5, 0.25)


@dataclasses.dataclass(frozen=True)
class Prior:
    """What the material query knows of one parameter: its ``value`` (the query's answer, or
    the median over the type's entries) and its plausible interval ``low``..``high`` (SI),
    from the knowledge-base entry ``entry`` (``how`` they were chosen)."""

    value: float
    low: float
    high: float
    entry: str
    how: str


def knowledge_priors(cfg: SceneConfig) -> dict[str, Prior]:
    """Per optimised material parameter (and density) of ``cfg`` (its materials resolved):
    the :class:`Prior` of its object (:func:`object_prior`); velocities and the clock have none."""
    from clflow.query.knowledge import load_knowledge_base

    kb = load_knowledge_base()
    out = {}
    for name in cfg.optimize.parameters:
        if name == TIME_SCALE.name:
            continue
        k, param = split_parameter(cfg.objects, name)
        if param != VELOCITY:
            prior = object_prior(kb, cfg.objects[k].material, param)
            if prior is not None:
                out[name] = prior
    return out


def object_prior(kb, material, param: str) -> Prior | None:
    """The prior of ``param`` (or density) of an object of ``material`` (a resolved
    MaterialConfig): with a material query's record (``query_result``) that matched an entry
    of the type, the query's answer and that entry's range; else the (lower) median of the
    values of the type's entries and the union of their ranges."""
    answer, entry = None, None
    if material.query_result is not None:
        from clflow.query.result import load_query_result

        record = load_query_result(material.query_result)
        answer = record.density if param == "density" else record.parameters.get(param)
        try:
            entry = kb.entry(record.matched) if record.matched else None
        except InputError:  # a foundation model's own name for the object
            entry = None
        entry = entry if entry is not None and entry.material == material.type else None
    if entry is not None:
        known = _known(entry, param)
        if known is None:
            return None
        value = known.value if answer is None else answer
        return Prior(value, min(known.low, value), max(known.high, value), entry.name, "the material query's match")
    known = [(e, k) for e in kb.entries if e.material == material.type for k in [_known(e, param)] if k is not None]
    if not known:
        return None
    middle, _ = sorted(known, key=lambda pair: pair[1].value)[(len(known) - 1) // 2]  # the lower median
    low, high = min(k.low for _, k in known), max(k.high for _, k in known)
    how = f"the median of the {material.type} entries, the union of their ranges"
    return Prior(_known(middle, param).value, low, high, middle.name, how)


def _known(entry, param: str):
    """The knowledge base's Value of ``param`` (or density) in ``entry``; None if it has none."""
    return entry.density if param == "density" else entry.parameters.get(param)


@dataclasses.dataclass(frozen=True)
class PriorDecision:
    """What the prior did to a fit: the final point ``z`` (the fit's own where nothing moved),
    the run there ``result`` (None where nothing moved), and ``record``, metrics.json's ``prior``."""

    z: dict[str, float]
    result: Evaluation | None
    record: dict


def decide(
    objective: Objective,
    z: dict[str, float],
    substeps: int,
    identifiability: dict,
    priors: dict[str, Prior],
) -> PriorDecision:
    """The prior's move from the fit ``z`` (run at ``substeps``), given its
    Diagnostics.identifiability report: each weakly constrained or unresolved parameter
    where the prior puts it (:func:`range_point`), the others refitted to first order,
    confirmed by a forward run within the model's loss tolerance (the module's docstring)."""
    problem = objective.problem
    variables = problem.main_variables
    weak = set(identifiability["weakly_constrained"]) | set(identifiability["unresolved"])
    unresolved = set(identifiability["unresolved"])
    targets = {
        name: range_point(problem, name, z, identifiability["ranges"][name], priors[name], name in unresolved)
        for name in variables
        if name in priors and name in weak and name in identifiability["ranges"]
    }
    targets = {name: t for name, t in targets.items() if t != z[name]}
    base, J = objective.jacobian(z, problem.frames, substeps, variables, problem.model_grid)
    loss = float((objective.residuals(base.flows, base.more_flows) ** 2).sum())
    limit = loss * (1 + identifiability["loss_tolerance"])
    move = refitted_move(J, variables, {name: t - z[name] for name, t in targets.items()})
    tried, kept, result = [], 0.0, None
    if targets:
        points = [moved(problem, z, move, fraction) for fraction in MOVE_FRACTIONS]
        runs = objective.evaluate_batch(points, problem.frames, min_substeps=substeps)
        for fraction, run in zip(MOVE_FRACTIONS, runs):
            if isinstance(run, (FloatingPointError, ClflowError)):
                tried.append({"fraction": fraction, "failed": str(run)})
                continue
            ratio = float((objective.residuals(run.flows, run.more_flows) ** 2).sum()) / max(loss, 1e-300)
            tried.append({"fraction": fraction, "loss_ratio": ratio})
            if ratio * loss <= limit:
                kept, result = fraction, run
                break
    final = moved(problem, z, move, kept) if kept else dict(z)
    fit_values, values = problem.values(z), problem.values(final)
    parameters = {}
    for name, prior in priors.items():
        if name not in variables:
            continue
        parameters[name] = {
            "prior": prior.value,
            "prior_range": [prior.low, prior.high],
            "entry": prior.entry,
            "how": prior.how,
            "video_fit": fit_values[name],
            "value": values[name],
            "decided_by": decided_by(name, targets, kept, priors, problem),
        }
    if targets and not kept:
        log.info(
            "the prior's move of %s leaves the loss tolerance at every fraction tried: kept the fit", sorted(targets)
        )
    record = {
        "source": "knowledge",
        "parameters": parameters,
        "move": {"fraction": kept, "tried": tried, "loss_limit_ratio": limit / max(loss, 1e-300)},
    }
    return PriorDecision(final, result, record)


def range_point(problem, name: str, z: dict[str, float], entry: dict, prior: Prior, unresolved: bool) -> float:
    """Where the prior puts ``name`` (z), within its range ``entry`` (Diagnostics.ranges: SI
    ends, None where open, then the box the search looked in): an ``unresolved`` one (the
    loss flat over a decade: any point there is the video's) at the prior's value; a weakly
    constrained one at the point of the prior's interval nearest the fit (the fit itself
    where that is plausible); either cut to the range."""
    p = problem.params[name]
    box = problem.box_of(name, z)
    low = box[0] if entry["low"] is None else float(p.encode(entry["low"]))
    high = box[1] if entry["high"] is None else float(p.encode(entry["high"]))
    wanted = z_of(p, prior.value) if unresolved else min(max(z[name], z_of(p, prior.low)), z_of(p, prior.high))
    return min(max(wanted, min(low, z[name])), max(high, z[name]))


def z_of(p, value: float) -> float:
    """z of ``value`` for parameterisation ``p``; -inf / +inf at or beyond an end no z reaches
    (0 on a log scale, a bounded parameter's valid ends)."""
    if p.param.scale == "log" and value <= 0:
        return -math.inf
    if p.param.scale == "bounded":
        lo, hi = p.bounds
        if value <= lo or value >= hi:
            return -math.inf if value <= lo else math.inf
    return float(p.encode(value))


def refitted_move(J: torch.Tensor, variables: tuple[str, ...], deltas: dict[str, float]) -> dict[str, float]:
    """Per variable its move in z when those of ``deltas`` move by them and the others are
    refitted to first order: the least-squares change of the rest that best cancels the
    residuals' change ``J`` [R, P] (columns in ``variables``' order) makes."""
    move = {name: deltas.get(name, 0.0) for name in variables}
    fixed = [i for i, name in enumerate(variables) if name in deltas]
    free = [i for i, name in enumerate(variables) if name not in deltas]
    if not fixed or not free:
        return move
    shift = J[:, fixed] @ torch.tensor([deltas[variables[i]] for i in fixed], dtype=J.dtype)
    refit = torch.linalg.lstsq(J[:, free], -shift[:, None]).solution[:, 0]
    for i, dz in zip(free, refit.tolist()):
        move[variables[i]] = dz
    return move


def moved(problem, z: dict[str, float], move: dict[str, float], fraction: float) -> dict[str, float]:
    """z moved by ``fraction`` of ``move``, each variable kept in its box (Problem.box_of)."""
    out = dict(z)
    for name, dz in move.items():
        low, high = problem.box_of(name, z)
        out[name] = min(max(z[name] + fraction * dz, low), high)
    return out


def decided_by(name: str, targets: dict[str, float], kept: float, priors: dict[str, Prior], problem) -> str:
    """Who set ``name``'s final value: ``video`` (the video determines it, its value is
    plausible, or the prior's move was not kept), ``prior`` (moved into the prior's
    interval, inside the video's range), ``range_end`` (moved to the end of the video's range
    nearest the interval, which the range does not reach) or ``prior_partly`` (a fraction of
    the move kept)."""
    if name not in targets or not kept:
        return "video"
    if kept < 1.0:
        return "prior_partly"
    p, prior = problem.params[name], priors[name]
    inside = z_of(p, prior.low) - 1e-12 <= targets[name] <= z_of(p, prior.high) + 1e-12
    return "prior" if inside else "range_end"


__all__ = ["Prior", "PriorDecision", "decide", "knowledge_priors"]
