"""How a run shows its progress: ``echo`` / ``note`` lines (the default shows nothing) and
one optimisation row as text."""

from __future__ import annotations

import contextlib
from typing import Callable


def _silent(line: str) -> None:
    """The default ``echo`` / ``note``: show nothing."""


def format_row(row: dict | None) -> str:
    """One optimisation progress row as text: loss, parameters and seconds per iteration."""
    if not row:
        return ""
    params = " ".join(f"{name}={value:.4g}" for name, value in row["params"].items())
    loss = "failed" if row["loss"] is None else f"{row['loss']:.4g}"
    if row.get("rejected"):
        loss = f"rejected (trial {loss})"
    start = f"start {row['start'] + 1}: " if "start" in row else ""  # a polish: iterations counted per start
    return f"{start}loss {loss}  {params}  {row['seconds']:.1f} s/it"


@contextlib.contextmanager
def iteration_lines(total: int, done: int, note: Callable[[str], None]):
    """A ``bar`` that notes one line per iteration (log files, CI): ``iteration k/total: row``."""
    yield lambda row: note(f"iteration {row['iteration'] + 1}/{total}: {format_row(row)}")


__all__ = ["format_row", "iteration_lines"]
