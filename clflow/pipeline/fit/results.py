"""The results of an optimisation: params.json, metrics.json, history.json, loss.png and a
comparison video per guidance view."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clflow.errors import ClflowError
from clflow.fileio import atomic_write_text
from clflow.pipeline.fit.budget import GridChoice
from clflow.pipeline.fit.checkpoint import Checkpoint
from clflow.pipeline.fit.diagnostics import MIN_LOSS_RISE, PROFILE_RISE, WEAK_STD_Z, Diagnostics
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.problem import Problem
from clflow.pipeline.fit.state import OptimizerState
from clflow.pipeline.forward import SimulationResult, render_frames
from clflow.pipeline.plots import range_text, write_history_plot
from clflow.scene.config import (
    TIME_SCALE,
    VELOCITY,
    SceneConfig,
    is_velocity_component,
    objects_form,
    split_parameter,
    velocity_names,
)

log = logging.getLogger(__name__)

# a fit that leaves more than this fraction of the observed motion unexplained (the squared
# flow residual over the observed flow's own) is warned of; what fits leave, clean, degraded,
# at a wrong playback speed: docs/pipeline.md, "A fit that does not explain the video"
UNEXPLAINED_WARNING = 0.10


def unexplained_warning(fraction: float) -> str:
    """The one line that says a fit leaves ``fraction`` of the observed motion unexplained, and why it may."""
    return (
        f"the fit leaves {100 * fraction:.0f} % of the observed motion unexplained (a video the model follows "
        f"leaves under {100 * UNEXPLAINED_WARNING:.0f} %): the video may play at another speed than real time "
        "(a generated one often does: add time_scale to optimize.parameters, or set simulation.fps to its frame "
        "rate divided by that speed), its camera may "
        "move in a way flow.stabilise did not take out (that needs flow.stabilise: static and some of the objects' "
        "still surroundings in view), "
        "or the material type may be wrong (optimize.material compares hypotheses)"
    )


def comparison_video(view: int) -> str:
    """The results' comparison video of guidance view ``view`` (0: the config's camera)."""
    return "comparison.mp4" if view == 0 else f"comparison_view{view}.mp4"


def parameter_unit(cfg: SceneConfig, name: str) -> str:
    """SI unit of an optimised variable (of a config with a concrete material; with several
    objects OBJECT.PARAM, of that object's)."""
    from clflow.materials import DENSITY, get_material

    if is_velocity_component(name):
        return "m/s"
    if name == TIME_SCALE.name:
        return TIME_SCALE.unit
    k, param = split_parameter(cfg.objects, name)
    return DENSITY.unit if param == "density" else get_material(cfg.objects[k].material.type).param(param).unit


def weak_reason(std_z: float, loss_rise: float) -> str:
    """Why Diagnostics.identifiability called a parameter weakly constrained, in words: its
    standard error (optimiser units, a lower bound) or the small loss a step costs."""
    if std_z > WEAK_STD_Z:
        return f"standard error {std_z:.2g} in the optimiser's units, above {WEAK_STD_Z:g} (a lower bound)"
    return (
        f"a step of {WEAK_STD_Z:g} in the optimiser's units, the others refitted, raises the loss by "
        f"{100 * loss_rise:.2g} %, under {100 * MIN_LOSS_RISE:g} %"
    )


@dataclass
class Results:
    """The results folder of a finished optimisation: its objective and diagnostics, the
    checkpoint its final calibration goes into, and what the run records beside them
    (``started``: time.perf_counter at its start; how the material was chosen, the guidance
    checks and the budget's grid choice)."""

    objective: Objective
    diagnostics: Diagnostics
    checkpoint: Checkpoint
    started: float
    hypotheses: dict | None = None
    guidance: list = field(default_factory=list)
    guidance_warnings: list[str] = field(default_factory=list)
    grid_choice: GridChoice | None = None

    @property
    def problem(self) -> Problem:
        return self.objective.problem

    def write_result_files(self, state: OptimizerState, out: Path) -> dict:
        """params.json, metrics.json, history.json (search.json), loss.png and a comparison
        video per guidance view in folder ``out`` (a staging folder of
        clflow.pipeline.runs.write_results, which moves them in as one step with run.json and
        index.html); returns the metrics."""
        result = self.final_evaluation(state)
        identifiability = self.diagnostics.identifiability(state.z, state.substeps, state.search)
        z, result, prior = self.prior_decision(state, result, identifiability)
        final = self.problem.values(z)
        metrics = self.result_metrics(state, result, identifiability, z)
        if prior is not None:
            metrics["prior"] = prior
        ranges = metrics["identifiability"]["ranges"]
        materials = [  # each object's material with its optimised values
            {"material": o.material.type, "parameters": v.params, "density": v.density, "velocity": list(v.velocity)}
            for o, v in zip(self.problem.cfg.objects, self.problem.object_values(final, self.problem.velocities(z)))
        ]
        record = {
            **objects_form(self.problem.cfg.objects, materials),
            "optimized": final,
            "units": {n: parameter_unit(self.problem.cfg, n) for n in final},
            # each optimised value's range (SI; None: open, the video only bounds the other side)
            "ranges": {n: {k: ranges[n][k] for k in ("low", "high", "level")} for n in final if n in ranges},
            # the substeps per frame the final evaluation needed (after any CFL retry): a
            # re-simulation of this result (clflow simulate --params-from) takes at least these
            "substeps": result.substeps,
            "fps": self.problem.cfg.simulation.fps,
        }
        atomic_write_text(out / "params.json", json.dumps(record, indent=2))
        atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2))
        atomic_write_text(out / "history.json", json.dumps(state.history, indent=1))
        if state.search:
            atomic_write_text(out / "search.json", json.dumps(state.search, indent=1))
        write_history_plot(out / "loss.png", state.history, self.problem.cfg.ground_truth, ranges)
        self.write_comparison_videos(result, out)
        return metrics

    def final_evaluation(self, state: OptimizerState):
        """The evaluation (with its Jacobian's base for the identifiability check) at the final
        parameters, or at the last accepted ones when those fail (``state`` changes in place and
        is saved); scored against the estimator's error there when the bias is corrected."""
        try:
            result, _ = self.objective.jacobian(
                state.z, self.problem.frames, state.substeps, self.problem.main_variables, self.problem.model_grid
            )
        except (FloatingPointError, ClflowError) as exc:
            if not state.history:
                raise
            good = state.history[-1]["z"]
            log.warning("the final parameters fail (%s): the results are those of the last good ones", exc)
            state.rollbacks.append(
                {
                    "iteration": state.iteration,
                    "phase": "final",
                    "reason": str(exc),
                    "params": self.problem.values(state.z),
                    "back_to": self.problem.values(good),
                }
            )
            state.z = dict(good)
            self.checkpoint.save(state)
            result, _ = self.objective.jacobian(
                state.z, self.problem.frames, state.substeps, self.problem.main_variables, self.problem.model_grid
            )
        if self.problem.corrects_bias:
            state.calibrated_at = self.objective.calibrate(
                state, result, self.problem.frames, self.objective.final_shifts
            ).calibrated_at
            self.checkpoint.save(state)
            result = self.objective.rescored(result)
        return result

    def prior_decision(self, state: OptimizerState, result, identifiability: dict) -> tuple[dict, object, dict | None]:
        """(the final point, its evaluation, metrics.json's ``prior`` or None): with
        ``optimize.prior: knowledge`` the prior's move from the fit (clflow.pipeline.fit.prior;
        the moved point's run scored against the estimator's error on its own simulation),
        else the fit's own."""
        if self.problem.cfg.optimize.prior != "knowledge":
            return state.z, result, None
        from clflow.pipeline.fit.prior import decide, knowledge_priors

        decision = decide(self.objective, state.z, state.substeps, identifiability, knowledge_priors(self.problem.cfg))
        for name, entry in decision.record["parameters"].items():
            if entry["decided_by"] != "video":  # every prior-decided value in one line each
                log.info(
                    "%s: %.4g (%s: the prior of %s), %.4g from the video alone",
                    name,
                    entry["value"],
                    entry["decided_by"],
                    entry["entry"],
                    entry["video_fit"],
                )
        if decision.result is None:
            return state.z, result, decision.record
        moved = decision.result
        if self.problem.corrects_bias:
            own = self.objective.self_consistent_loss(moved, self.problem.frames, self.objective.final_shifts)
            moved = dataclasses.replace(moved, loss=own)
        return decision.z, moved, decision.record

    def result_metrics(
        self, state: OptimizerState, result, identifiability: dict | None = None, z: dict[str, float] | None = None
    ) -> dict:
        """metrics.json: the loss and end-point error at the final parameters (``z``, default
        state.z), the iterations, the grids (and the budget's choice), the seconds, the
        rollbacks, the guidance checks, how much of the observed motion the fit leaves
        unexplained (a warning above UNEXPLAINED_WARNING), the identifiability at state.z (its
        warnings logged; ``identifiability``: already measured) and the relative error against
        the config's ground truth when it has one."""
        z = state.z if z is None else z
        final = self.problem.values(z)
        metrics = {
            "flow_loss": result.loss,
            "epe_px": self.objective.endpoint_error(result.flows, result.more_flows),
            "iterations": len(state.history),
            "seconds_per_iteration": float(np.mean([h["seconds"] for h in state.history])) if state.history else 0.0,
        }
        metrics["grid"] = {
            "main": self.problem.model_grid,
            "search": self.problem.search_grid,
        }  # nodes along the longest side
        metrics["identifiability"] = (
            self.diagnostics.identifiability(state.z, state.substeps, state.search)
            if identifiability is None
            else identifiability
        )
        # in this process: setup, the guidance's flow, search, iterations and the diagnostics above
        metrics["seconds"] = time.perf_counter() - self.started
        if self.grid_choice is not None:  # optimize.budget chose the main grid
            metrics["budget"] = dataclasses.asdict(self.grid_choice)
        metrics["rollbacks"] = state.rollbacks  # every rejected iteration: its reason and parameters
        if state.line_search is not None:  # the line search of the own-calibration loss after LM
            metrics["line_search"] = state.line_search
        if self.guidance:
            metrics["guidance_checks"] = [check.record() for check in self.guidance]
        if any(view.stabilisation is not None for view in self.problem.views):  # per view: what flow.stabilise removed
            metrics["stabilisation"] = [view.stabilisation for view in self.problem.views]
        if self.guidance_warnings:  # forced past a failed guidance check (--force-video)
            metrics["warnings"] = list(self.guidance_warnings)
        metrics["unexplained_motion"] = self.objective.unexplained_motion(result)
        if metrics["unexplained_motion"]["fraction"] > UNEXPLAINED_WARNING:
            line = unexplained_warning(metrics["unexplained_motion"]["fraction"])
            log.warning("%s", line)
            metrics.setdefault("warnings", []).append(line)
        self.warn_identifiability(metrics["identifiability"])
        if self.hypotheses:
            metrics["material_hypotheses"] = self.hypotheses
        truth = self.problem.cfg.ground_truth
        if truth:
            metrics["relative_error"] = {
                n: abs(final[n] - truth[n]) / abs(truth[n]) for n in self.problem.params if n in truth
            }
            errors = {}  # |v - v_true| (m/s) by velocity_names' name
            for k, velocity in enumerate(self.problem.velocities(z)):
                name, components = velocity_names(self.problem.cfg.objects, k)
                if components[0] not in final or components[0] not in truth:
                    continue
                true_velocity = [truth[n] for n in components]
                errors[name] = math.dist(velocity, true_velocity)
                if any(true_velocity):
                    metrics["relative_error"][name] = errors[name] / math.hypot(*true_velocity)
            if errors:  # the one object's (named plain velocity) alone, else by OBJECT.velocity
                metrics["velocity_error_m_s"] = errors.get(VELOCITY, errors)
        return metrics

    def warn_identifiability(self, identifiability: dict) -> None:
        """Each variable's range (INFO), and a warning per parameter the video constrains
        weakly, does not resolve, or that depends on the grid, and per pair that trades off
        (Diagnostics.identifiability)."""
        for name, entry in identifiability["ranges"].items():
            log.info(
                "%s = %.4g, %d %% range %s",
                name,
                entry["value"],
                round(100 * entry["level"]),
                range_text(entry, parameter_unit(self.problem.cfg, name)),
            )
        for name in identifiability["weakly_constrained"]:
            reason = weak_reason(identifiability["std_z"][name], identifiability["loss_rise"][name])
            log.warning("%s is weakly constrained by the video: %s; its value is uncertain", name, reason)
        for name in identifiability["unresolved"]:
            values = identifiability["profile"][name]["values"]
            log.warning(
                "%s is not resolved by the video from %.3g to %.3g (SI): moved alone there, the loss changes by "
                "less than %d %%",
                name,
                min(values),
                max(values),
                round(100 * PROFILE_RISE),
            )
        coarse_grid = identifiability["grids"][0]
        for name in identifiability["grid_sensitive"]:
            log.warning(
                "%s depends on the grid: on %d nodes instead of %d its best fit moves by %+.2g in the "
                "optimiser's units; its value carries a discretisation error of about that size",
                name,
                coarse_grid,
                self.problem.model_grid,
                identifiability["grid_shift_z"][name],
            )
        for a, b, rho in identifiability["trade_offs"]:
            log.warning("%s and %s trade off (correlation %.3f): the video fixes a combination of them", a, b, rho)

    def write_comparison_videos(self, result, out) -> None:
        """Per guidance view, side by side: guidance | guidance flow | simulated flow | error,
        and the simulated frames from that view (out/comparison.mp4, comparison_view1.mp4, ...)."""
        from clflow.flow.visualize import comparison_panel
        from clflow.media import write_video

        traj = result.trajectory
        simulated = SimulationResult(self.problem.prepared, traj.x.detach(), traj.F.detach())
        for k, (view, view_flows) in enumerate(zip(self.problem.views, [result.flows, *result.more_flows])):
            sim_frames = render_frames(simulated, camera=view.camera)
            max_flow = max(float(view.observed.norm(dim=-1).max()), 1e-6)
            panels = [
                np.concatenate(
                    [
                        comparison_panel(
                            view.video_frames[t], view.observed[t].numpy(), view_flows[t].numpy(), max_flow
                        ),
                        sim_frames[t],
                    ],
                    1,
                )
                for t in range(self.problem.frames)
            ]
            write_video(out / comparison_video(k), np.stack(panels), self.problem.cfg.simulation.fps)
