"""How the search's starts are polished (``Optimization.map_starts``): one after another in
this process, or each a Ray task (``clflow optimize --parallel``).

A mapper takes the run, the state the search ended in, the indices of the starts to polish,
whether to resume their checkpoints and the most iterations they may run now, and returns the records of
``Optimization.polish`` in start order. The run only needs ``polish``, ``progress`` and
``task_copy`` (:class:`PolishesStarts`), so this module does not import the driver.
"""

from __future__ import annotations

from typing import Callable, Iterable, Protocol

from clflow.pipeline.fit.state import OptimizerState


class PolishesStarts(Protocol):
    """What a mapper asks of the run (clflow.pipeline.fit.driver.Optimization)."""

    def polish(
        self, begin: OptimizerState, start: int, resume: bool = False, max_iterations: int | None = None
    ) -> dict: ...

    def progress(self, row: dict) -> None: ...

    def task_copy(self) -> PolishesStarts: ...


def quiet(row: dict) -> None:
    """No progress shown (a Ray task's: its rows are shown where its record arrives)."""


def serial_starts(
    opt: PolishesStarts,
    begin: OptimizerState,
    starts: Iterable[int],
    resume: bool = False,
    max_iterations: int | None = None,
) -> list[dict]:
    """Polish each of ``starts`` (indices into begin.starts) one after another in this process
    (``max_iterations``: at most this many in all); records of Optimization.polish."""
    records = []
    for k in starts:
        records.append(opt.polish(begin, k, resume=resume, max_iterations=max_iterations))
        if max_iterations is not None:
            max_iterations -= records[-1]["iterations_here"]
    return records


def _polish_task(opt: PolishesStarts, begin: OptimizerState, start: int, resume: bool) -> dict:
    return opt.polish(begin, start, resume=resume)


def starts_on_ray(**ray_options) -> Callable[..., list[dict]]:
    """A mapper whose every start's polish is a Ray task (clflow.parallel.map_on_ray,
    ``ray_options`` its keywords) of the run's :meth:`task_copy`, its rows shown as it finishes."""

    def map_starts(
        opt: PolishesStarts, begin: OptimizerState, starts: Iterable[int], resume: bool = False, max_iterations=None
    ) -> list[dict]:
        from clflow.parallel import map_on_ray

        def finished(index: int, record: dict) -> None:
            for row in record["state"]["history"][len(begin.history) :]:
                opt.progress(row)

        task = opt.task_copy()
        return map_on_ray(_polish_task, [(task, begin, k, resume) for k in starts], done=finished, **ray_options)

    return map_starts
