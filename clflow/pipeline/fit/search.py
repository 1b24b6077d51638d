"""The global search of an optimisation and the polish of its best starts: one after
another in this process (:func:`serial_starts`), or each a Ray task (:func:`starts_on_ray`,
``clflow optimize --parallel``)."""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import asdict
from typing import Callable, Iterable

import torch

from clflow.errors import ClflowError
from clflow.fileio.reading import parse_json
from clflow.limits import format_duration
from clflow.pipeline.fit.checkpoint import Checkpoint
from clflow.pipeline.fit.iteration import Iterations
from clflow.pipeline.fit.objective import Objective
from clflow.pipeline.fit.problem import Problem
from clflow.pipeline.fit.state import LM_DAMPING, OptimizerState, config_digests
from clflow.pipeline.fit.steps import Steps

log = logging.getLogger(__name__)


def quiet(row: dict) -> None:
    """No progress shown (a Ray task's: its rows are shown where its record arrives)."""


class SearchDesign:
    """Where the global search of a problem samples: its box around the start, the first
    round's Sobol design, an object's round, the second round's neighbourhoods."""

    def __init__(self, problem: Problem):
        self.problem = problem

    def search_points(self, z0: dict[str, float]) -> list[dict[str, float]]:
        """The global phase's design: the start, then a scrambled Sobol sequence (seed 0,
        reproducible) over the search box."""
        box = self.problem.search_box(z0)
        names = list(self.problem.params)
        count = self.problem.cfg.optimize.search.samples
        unit = torch.quasirandom.SobolEngine(len(names), scramble=True, seed=0).draw(
            max(0, count - 1), dtype=torch.float64
        )
        points = [dict(z0)]
        for row in unit.tolist():
            points.append({**z0, **{n: box[n][0] + u * (box[n][1] - box[n][0]) for n, u in zip(names, row)}})
        return points

    def object_points(self, names: tuple[str, ...], held: dict[str, float], z0: dict[str, float], seed: int):
        """An object round's design: ``search.object_samples`` per parameter of the object
        (``names``) over its own part of the search box, a scrambled Sobol sequence (``seed``),
        every other parameter at ``held``. Objects meet only through contact, so one object's
        best parameters hardly move with another's: a joint design of n samples resolves each
        of d parameters at n^(1/d) values, an object's round at its own count."""
        box = self.problem.search_box(z0)
        count = self.problem.cfg.optimize.search.object_samples * len(names)
        unit = torch.quasirandom.SobolEngine(len(names), scramble=True, seed=seed).draw(count, dtype=torch.float64)
        return [
            {**held, **{n: box[n][0] + u * (box[n][1] - box[n][0]) for n, u in zip(names, row)}}
            for row in unit.tolist()
        ]

    def neighbourhoods(
        self, rows: list[dict], z0: dict[str, float]
    ) -> list[tuple[int, dict[str, tuple[float, float]]]]:
        """The second round's regions: (index into ``rows``, box in z) around each of the best
        ``search.starts`` samples of the rounds before (``rows``) that lie outside each other's
        box, best first. A box spans one first-round spacing per parameter (the search box's
        width / samples^(1/parameters)) centred on its sample, cut to the search box."""
        box, names = self.problem.search_box(z0), list(self.problem.params)
        count = self.problem.cfg.optimize.search.samples
        spacing = {n: (box[n][1] - box[n][0]) * count ** (-1.0 / len(names)) for n in names}
        ranked = sorted((i for i, r in enumerate(rows) if r["loss"] is not None), key=lambda i: rows[i]["loss"])
        centres: list[int] = []
        for i in ranked:
            if len(centres) == self.problem.cfg.optimize.search.starts:
                break
            z = rows[i]["z"]
            if all(max(abs(z[n] - rows[c]["z"][n]) / spacing[n] for n in names) > 0.5 for c in centres):
                centres.append(i)
        return [
            (
                i,
                {
                    n: (
                        max(box[n][0], rows[i]["z"][n] - spacing[n] / 2),
                        min(box[n][1], rows[i]["z"][n] + spacing[n] / 2),
                    )
                    for n in names
                },
            )
            for i in centres
        ]

    def refinement_points(
        self, regions: list[tuple[int, dict[str, tuple[float, float]]]], z0: dict[str, float]
    ) -> list[tuple[int, dict[str, float]]]:
        """The second round's design: (centre's index, z) for ``search.refine`` samples shared
        among the :meth:`neighbourhoods` ``regions`` (the first refine % regions one more),
        a scrambled Sobol sequence (seed 1) in each."""
        if not regions:
            return []
        names, total = list(self.problem.params), self.problem.cfg.optimize.search.refine
        counts = [total // len(regions) + (k < total % len(regions)) for k in range(len(regions))]
        unit = torch.quasirandom.SobolEngine(len(names), scramble=True, seed=1).draw(max(counts), dtype=torch.float64)
        return [
            (i, {**z0, **{n: region[n][0] + u * (region[n][1] - region[n][0]) for n, u in zip(names, row)}})
            for (i, region), count in zip(regions, counts)
            for row in unit[:count].tolist()
        ]


class Search:
    """The global phase (optimize.search) of a problem and its objective: samples of a box
    around the start, a second round around the best, each of the best polished by a few
    Levenberg-Marquardt iterations (:class:`StartPolish`), the best polish kept on the main
    grid. Every sample goes into ``checkpoint``; under ``optimize.budget`` the search ends
    once ``deadline`` seconds after ``started`` (time.perf_counter) have passed."""

    def __init__(
        self,
        objective: Objective,
        checkpoint: Checkpoint,
        started: float,
        deadline: float | None = None,
    ):
        self.objective = objective
        self.problem = objective.problem
        self.design = SearchDesign(objective.problem)
        self.checkpoint = checkpoint
        self.started = started
        self.deadline = deadline

    def global_search(self, state: OptimizerState, progress: Callable[[dict], None] = quiet) -> OptimizerState:
        """Forward-only losses at the search design; with parameters of several objects, a
        round per object (:meth:`object_points`, in the config's order, each holding the
        others at the best sample so far); then (``search.refine``) a second round around the
        best distinct samples (resuming after the samples already in ``state.search``);
        returns the state with z at the best sample, ``searched`` and the starts: the best
        sample of each neighbourhood with a second round, else the best ``search.starts``
        samples. With ``flow.bias_correction``, each sample's loss is against the observed
        flow less the estimator's error on that sample's own simulation (the video's
        estimated flow against the simulation's, estimated alike). Under ``optimize.budget``
        it ends early once past its deadline, skipping what is left of its rounds
        (search_overran)."""
        settings = self.problem.cfg.optimize.search
        frames = min(self.problem.frames, settings.frames or self.problem.frames)
        rows = list(state.search)
        objects = self.problem.cfg.optimize.parameters_by_object() if settings.object_samples else {}
        planned = settings.samples + self.problem.cfg.optimize.object_round_samples() + settings.refine

        def run_round(points: list[tuple[dict[str, float], dict]]) -> bool:
            """Sample ``points`` ((z, what the row records of its round)) as one batch, a row
            and a checkpoint as each is known; False once the budget cut it short."""
            nonlocal state
            results = self.objective.evaluate_batch([z for z, _ in points], frames, grid=self.problem.search_grid)
            for z, round_of in points:
                if self.search_overran(rows, planned):
                    return False
                start = time.perf_counter()
                try:
                    result = next(results)
                    if isinstance(result, Exception):
                        raise result
                    loss = self.objective.self_consistent_loss(result, frames)
                except (FloatingPointError, ClflowError) as exc:
                    log.info("search sample %s failed: %s", self.problem.values(z), exc)
                    loss = None
                rows.append(
                    {"z": z, "params": self.problem.values(z), "loss": loss, "frames": frames, **round_of}
                    | {"grid": self.problem.search_grid, "seconds": time.perf_counter() - start}
                )
                state = dataclasses.replace(state, search=list(rows))
                self.checkpoint.save(state)
                progress({**rows[-1], "phase": "search", "iteration": len(rows) - 1})
            return True

        design = self.design.search_points(state.z)
        complete = run_round([(z, {}) for z in design[len(rows) :]])  # not cut short by the budget
        if not any(r["loss"] is not None for r in rows):
            raise ClflowError(f"the global search found no parameters whose simulation ran ({len(rows)} samples)")
        done = len(design)
        for seed, (name, names) in enumerate(objects.items() if complete else (), start=2):
            held = min((r for r in rows[:done] if r["loss"] is not None), key=lambda r: r["loss"])
            points = self.design.object_points(names, held["z"], state.z, seed)
            complete = run_round([(z, {"object": name}) for z in points[len(rows) - done :]])
            if not complete:
                break
            done += len(points)
        regions = self.design.neighbourhoods(rows[:done], state.z) if settings.refine and complete else []
        refinement = self.design.refinement_points(regions, state.z)[len(rows) - done :]
        run_round([(z, {"around": around}) for around, z in refinement])
        ranked = sorted((r for r in rows if r["loss"] is not None), key=lambda r: r["loss"])
        best = ranked[0]
        log.info("global search: best of %d samples %s (loss %.4g)", len(rows), best["params"], best["loss"])
        if regions:  # each neighbourhood's best, its centre included
            groups = [[rows[i]] + [r for r in rows[done:] if r.get("around") == i] for i, _ in regions]
            picks = sorted(
                (min(g, key=lambda r: r["loss"] if r["loss"] is not None else math.inf) for g in groups),
                key=lambda r: r["loss"],
            )
        else:
            picks = ranked[: settings.starts]
        starts = [dict(r["z"]) for r in picks] if settings.starts > 1 else []
        state = dataclasses.replace(state, z=dict(best["z"]), searched=True, starts=starts)
        self.checkpoint.save(state)
        return state

    def search_overran(self, rows: list[dict], planned: int) -> bool:
        """With ``optimize.budget``: True (and a warning) once a sample has succeeded and the
        search has passed ``search_deadline``, the moment that leaves the rest of the run its
        predicted time on the coarsest main grid; the search then ends with the samples it has
        (``planned``: how many it meant to run). The deadline counts from this process's
        start: a resumed search gets its full share again."""
        if self.deadline is None or not any(r["loss"] is not None for r in rows):
            return False
        spent = time.perf_counter() - self.started
        if spent <= self.deadline:
            return False
        log.warning(
            "budget: the search stopped after %d of %d samples, %s into the run: the rest is predicted to take "
            "%s of the budget's %s",
            len(rows),
            planned,
            format_duration(spent),
            format_duration(self.problem.cfg.optimize.budget.seconds - self.deadline),
            format_duration(self.problem.cfg.optimize.budget.seconds),
        )
        return True

    def keep_best_start(self, begin: OptimizerState, records: list[dict]) -> OptimizerState:
        """The state after every start's polish (``records`` of :meth:`polish`, in start
        order, from ``begin``): their rows and rollbacks one after another, iterations
        numbered on; each start's best point in ``polished``; z at the best of them, with its
        substeps and calibration, and Levenberg-Marquardt's memory reset. With a coarser
        search grid the best is the one whose loss is least on the main phase's grid (each
        against the estimator's error at its own point), where the result comes from."""
        history, rollbacks, polished, ends = list(begin.history), list(begin.rollbacks), [], []
        iteration = begin.iteration
        for record in records:
            end = OptimizerState(**record["state"])
            shift = iteration - begin.iteration
            history += [{**r, "iteration": r["iteration"] + shift} for r in end.history[len(begin.history) :]]
            rollbacks += [{**r, "iteration": r["iteration"] + shift} for r in end.rollbacks[len(begin.rollbacks) :]]
            iteration += end.iteration - begin.iteration
            polished.append(
                {
                    "z": dict(end.best["z"]),
                    "loss": end.best["loss"],
                    "params": self.problem.values(end.best["z"]),
                    "substeps": end.substeps,
                }
            )
            ends.append(end)
        ranking = "loss"
        if self.problem.search_grid != self.problem.model_grid and len(polished) > 1:
            ranking = "model_loss"
            runs = self.objective.evaluate_batch(
                [r["z"] for r in polished], self.problem.frames, min_substeps=[r["substeps"] for r in polished]
            )
            for record, result in zip(polished, runs):
                try:
                    if isinstance(result, Exception):
                        raise result
                    record["model_loss"] = self.objective.self_consistent_loss(result, self.problem.frames)
                except (FloatingPointError, ClflowError) as exc:
                    log.info("start %s fails on the main phase's grid: %s", record["params"], exc)
                    record["model_loss"] = math.inf
        index = min(range(len(polished)), key=lambda i: polished[i][ranking])
        kept = polished[index]
        log.info(
            "kept start %d of %d: %s (%s %.4g; the others %s)",
            index,
            len(polished),
            kept["params"],
            "loss on the main phase's grid" if ranking == "model_loss" else "loss",
            kept[ranking],
            ", ".join(f"{r[ranking]:.4g}" for r in polished if r is not kept),
        )
        state = dataclasses.replace(
            begin,
            iteration=iteration,
            history=history,
            rollbacks=rollbacks,
            polished=polished,
            z=dict(kept["z"]),
            substeps=kept["substeps"],
            best=None,
            damping=LM_DAMPING,
            converged=False,
            calibrated_at=ends[index].calibrated_at,
        )
        self.objective.restore_estimator_errors(state.calibrated_at, records[index]["errors"])
        return state


class StartPolish:
    """Levenberg-Marquardt from a search start of the run's objective, as if no other start
    ran: a fork of the objective (a calibration of its own), iterations and a checkpoint of
    its own, in ``output/starts/<start>/``."""

    def __init__(self, objective: Objective):
        self.objective = objective
        self.problem = objective.problem

    def detached(self) -> StartPolish:
        """The polisher a Ray task gets (:func:`starts_on_ray`): the run's objective
        without its cached Jacobians."""
        return StartPolish(self.objective.fork(self.objective.calibration_file))

    def polish(
        self,
        begin: OptimizerState,
        start: int,
        resume: bool = False,
        max_iterations: int | None = None,
        progress: Callable[[dict], None] = quiet,
    ) -> dict:
        """Levenberg-Marquardt from search start ``start`` (``begin``: the state the search
        ended in) for ``search.start_iterations`` iterations or until it converges: its own
        time step (substeps from 1; the first start keeps begin's), calibration, rollbacks
        and horizon schedule (``resume`` goes on from its checkpoint; ``max_iterations``: at
        most this many now; ``progress`` gets each iteration's row). Returns {"state": its
        end state (asdict), "errors": each view's estimator error [T, H, W, 2] at its end
        (None without a calibration), "finished", "iterations_here"}."""
        folder = self.problem.cfg.output / "starts" / str(start)
        z0 = dict(begin.starts[start])
        objective = self.objective.fork(folder / "estimator_error.npz")
        iterations = Iterations(Steps(objective))
        checkpoint = Checkpoint(folder / "checkpoint.json", self.problem)
        state = self.load(checkpoint, objective, z0) if resume else None
        if state is None:
            state = dataclasses.replace(
                begin,
                z=z0,
                substeps=begin.substeps if start == 0 else 1,
                best=None,
                damping=LM_DAMPING,
                converged=False,
                calibrated_at=None,
                history=list(begin.history),
                rollbacks=list(begin.rollbacks),
            )
        failures, done = 0, 0
        last = state.history[-1] if state.history else {}
        finished = last.get("start") == start and bool(last.get("start_done"))
        while not finished and (max_iterations is None or done < max_iterations):
            state, failures, row = iterations.step(state, failures, start)
            if row is None:
                continue
            finished, done = bool(row.get("start_done")), done + 1
            checkpoint.save(state, start=z0)
            progress(row)
        errors = None if state.calibrated_at is None else [e.numpy() for e in objective.errors]
        return {"state": asdict(state), "errors": errors, "finished": finished, "iterations_here": done}

    def load(self, checkpoint: Checkpoint, objective: Objective, z0: dict[str, float]) -> OptimizerState | None:
        """A start's polish as saved in ``checkpoint`` (its calibration restored into
        ``objective``), None when there is none of this config and start point."""
        try:
            data = parse_json(checkpoint.path.read_text())
            state = OptimizerState(**data["state"])
        except (OSError, ValueError, KeyError, TypeError):
            return None
        cfg = self.problem.cfg
        if data.get("start") != z0 or data.get("config_digests") not in (
            config_digests(cfg),
            config_digests(cfg, by_path=True),
        ):
            return None
        if state.calibrated_at is not None:
            objective.restore_calibration(state)
        return state


#: A mapper of the starts' polishes (``Optimization.map_starts``): (the polisher, the state
#: the search ended in, the indices of the starts to polish, whether to resume their
#: checkpoints, where their rows go) -> the records of StartPolish.polish in start order.
StartsMapper = Callable[[StartPolish, OptimizerState, Iterable[int], bool, Callable[[dict], None]], list[dict]]


def serial_starts(
    polisher: StartPolish,
    begin: OptimizerState,
    starts: Iterable[int],
    resume: bool = False,
    progress: Callable[[dict], None] = quiet,
    max_iterations: int | None = None,
) -> list[dict]:
    """Polish each of ``starts`` (indices into begin.starts) one after another in this process
    (``max_iterations``: at most this many in all), each row to ``progress``; records of
    StartPolish.polish. A :data:`StartsMapper`."""
    records = []
    for k in starts:
        records.append(polisher.polish(begin, k, resume, max_iterations, progress))
        if max_iterations is not None:
            max_iterations -= records[-1]["iterations_here"]
    return records


def _polish_task(polisher: StartPolish, begin: OptimizerState, start: int, resume: bool) -> dict:
    return polisher.polish(begin, start, resume=resume)


def starts_on_ray(**ray_options) -> StartsMapper:
    """A mapper whose every start's polish is a Ray task (clflow.parallel.map_on_ray,
    ``ray_options`` its keywords), its rows shown as it finishes."""

    def map_starts(polisher, begin, starts, resume, progress):
        from clflow.parallel import map_on_ray

        def finished(index: int, record: dict) -> None:
            for row in record["state"]["history"][len(begin.history) :]:
                progress(row)

        detached = polisher.detached()
        tasks = [(detached, begin, k, resume) for k in starts]
        return map_on_ray(_polish_task, tasks, done=finished, **ray_options)

    return map_starts
