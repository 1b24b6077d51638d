"""Progress of long commands: a bar on a terminal, a line per tenth of the work otherwise."""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Callable, Iterator

import click


@contextmanager
def progress(
    total: int, label: str, show: Callable | None = None, done: int = 0, every: int | None = None
) -> Iterator[Callable[..., None]]:
    """Yields ``advance(item=None, to=None)``, to call as the work goes: one unit more, or up
    to unit ``to``. On a terminal a click progress bar on stderr (``show(item)`` beside it);
    otherwise a line ``label: k/total shown`` on stderr after every ``every`` units (default
    a tenth of the work) and at the end, so that log files and CI get a few lines, not a
    redrawn bar. ``done``: units finished before (a resumed run)."""
    show = show or (lambda item: "" if item is None else str(item))
    if sys.stderr.isatty():
        with click.progressbar(
            length=total,
            label=label,
            show_pos=True,
            file=sys.stderr,
            item_show_func=lambda item: None if item is None else show(item),
        ) as bar:
            bar.update(done)
            yield lambda item=None, to=None: bar.update(1 if to is None else to - bar.pos, item)
        return
    position = [done]
    step = every or max(1, total // 10)

    def advance(item=None, to: int | None = None) -> None:
        position[0] = position[0] + 1 if to is None else to
        if position[0] % step == 0 or position[0] == total:
            click.echo(f"{label}: {position[0]}/{total} {show(item)}".rstrip(), err=True)

    yield advance


def note(line: str) -> None:
    """A progress line, on stderr (results go to stdout)."""
    click.echo(line, err=True)


def iteration_bar(total: int, done: int):
    """The ``bar`` of :func:`clflow.pipeline.runs.run_optimization`: a click progress bar of
    the iterations (each row shown beside it) on a terminal, else one line per iteration."""
    from clflow.pipeline.runs import format_row, iteration_lines

    if not sys.stderr.isatty():
        return iteration_lines(total, done, note)
    return progress(total, "optimising", show=format_row, done=done)


__all__ = ["iteration_bar", "note", "progress"]
