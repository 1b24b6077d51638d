"""Progress of long commands: a bar on a terminal, a line per tenth of the work otherwise."""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Callable, Iterator

import click


@contextmanager
def progress(total: int, label: str) -> Iterator[Callable[[str], None]]:
    """Yields ``advance(item="")``, to call once per unit of ``total``: a click progress bar
    on stderr when it is a terminal, else a line ``label: k/total item`` after each tenth of
    the work (log files and CI get a few lines, not a redrawn bar)."""
    if sys.stderr.isatty():
        with click.progressbar(length=total, label=label, show_pos=True, file=sys.stderr,
                               item_show_func=lambda item: item) as bar:
            yield lambda item="": bar.update(1, item)
        return
    done = [0]
    step = max(1, total // 10)

    def advance(item: str = "") -> None:
        done[0] += 1
        if done[0] % step == 0 or done[0] == total:
            click.echo(f"{label}: {done[0]}/{total} {item}".rstrip(), err=True)

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
    return _bar(total, done, format_row)


@contextmanager
def _bar(total: int, done: int, show: Callable[[dict], str]) -> Iterator[Callable[[dict], None]]:
    with click.progressbar(length=total, label="optimising", show_pos=True, item_show_func=show,
                           file=sys.stderr) as bar:
        bar.update(done)
        yield lambda row: bar.update(1, row)


__all__ = ["iteration_bar", "note", "progress"]
