"""How the search's starts are polished (``Optimization.map_starts``): one after another in
this process, or each a Ray task (``clflow optimize --parallel``).

A mapper takes the polisher (clflow.pipeline.fit.search.StartPolish), the state the search
ended in, the indices of the starts to polish, whether to resume their checkpoints, the most
iterations they may run now and where their rows go, and returns the records of
``StartPolish.polish`` in start order. It needs only ``polish`` and ``detached``
(:class:`PolishesStarts`), so this module imports neither the search nor the driver.
"""

from __future__ import annotations

from typing import Callable, Iterable, Protocol

from clflow.pipeline.fit.state import OptimizerState


def quiet(row: dict) -> None:
    """No progress shown (a Ray task's: its rows are shown where its record arrives)."""


class PolishesStarts(Protocol):
    """What a mapper asks of the polisher (clflow.pipeline.fit.search.StartPolish)."""

    def polish(
        self,
        begin: OptimizerState,
        start: int,
        resume: bool = False,
        max_iterations: int | None = None,
        progress: Callable[[dict], None] = quiet,
    ) -> dict: ...

    def detached(self) -> PolishesStarts: ...


def serial_starts(
    polisher: PolishesStarts,
    begin: OptimizerState,
    starts: Iterable[int],
    resume: bool = False,
    max_iterations: int | None = None,
    progress: Callable[[dict], None] = quiet,
) -> list[dict]:
    """Polish each of ``starts`` (indices into begin.starts) one after another in this process
    (``max_iterations``: at most this many in all), each row to ``progress``; records of
    StartPolish.polish."""
    records = []
    for k in starts:
        records.append(polisher.polish(begin, k, resume, max_iterations, progress))
        if max_iterations is not None:
            max_iterations -= records[-1]["iterations_here"]
    return records


def _polish_task(polisher: PolishesStarts, begin: OptimizerState, start: int, resume: bool) -> dict:
    return polisher.polish(begin, start, resume=resume)


def starts_on_ray(**ray_options) -> Callable[..., list[dict]]:
    """A mapper whose every start's polish is a Ray task (clflow.parallel.map_on_ray,
    ``ray_options`` its keywords), its rows shown as it finishes."""

    def map_starts(
        polisher: PolishesStarts,
        begin: OptimizerState,
        starts: Iterable[int],
        resume: bool = False,
        max_iterations: int | None = None,
        progress: Callable[[dict], None] = quiet,
    ) -> list[dict]:
        from clflow.parallel import map_on_ray

        def finished(index: int, record: dict) -> None:
            for row in record["state"]["history"][len(begin.history) :]:
                progress(row)

        detached = polisher.detached()
        tasks = [(detached, begin, k, resume) for k in starts]
        return map_on_ray(_polish_task, tasks, done=finished, **ray_options)

    return map_starts
