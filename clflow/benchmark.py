"""Timing for ``clflow bench ...``: one way to warm up, repeat, and take wall and CPU time and
the machine's load, and one record of the figures (``--json``).

    timing = measure(lambda: rasterize(...), repeats=10)   # one untimed warm-up call first
    timing.median_wall, timing.median_cpu                  # s
    with watch:                                             # a Stopwatch: time any block
        loss.backward()
    write_record("bench.json", "raster", {"size": 512}, {"forward": timing.record()})

CPU time is that of every thread of this process (the OpenCL CPU driver's workers
included), so on a machine shared with other jobs it barely moves while the wall time grows
with the load; both are kept, with the 1-minute load average before and after.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from clflow.environment import load_average


@dataclass
class Timing:
    """Wall and CPU seconds of each timed run, the load average before the first and after
    the last, and ``result``: what the last run returned."""

    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    load_before: float | None = None
    load_after: float | None = None
    result: Any = None

    @property
    def median_wall(self) -> float:
        return statistics.median(self.wall)

    @property
    def median_cpu(self) -> float:
        return statistics.median(self.cpu)

    @property
    def best_wall(self) -> float:
        return min(self.wall)

    def record(self) -> dict:
        """The figures as JSON-ready numbers (seconds; ``cores``: the machine's CPU count)."""
        return {
            "runs": len(self.wall),
            "median_wall_s": self.median_wall,
            "median_cpu_s": self.median_cpu,
            "best_wall_s": self.best_wall,
            "wall_s": self.wall,
            "cpu_s": self.cpu,
            "load_before": self.load_before,
            "load_after": self.load_after,
            "cores": os.cpu_count(),
        }


class Stopwatch:
    """Times each ``with watch:`` block (wall and CPU seconds); ``timing(skip)`` leaves out
    the first ``skip`` blocks (warm-ups). A block that raises is not counted."""

    def __init__(self) -> None:
        self._timing = Timing()
        self._start: tuple[float, float] | None = None

    def __enter__(self) -> Stopwatch:
        if self._timing.load_before is None:
            self._timing.load_before = load_average()
        self._start = (time.perf_counter(), time.process_time())
        return self

    def __exit__(self, kind, value, traceback) -> None:
        wall, cpu = time.perf_counter() - self._start[0], time.process_time() - self._start[1]
        if kind is None:
            self._timing.wall.append(wall)
            self._timing.cpu.append(cpu)

    def timing(self, skip: int = 0) -> Timing:
        t = self._timing
        return Timing(t.wall[skip:], t.cpu[skip:], t.load_before, load_average(), t.result)


def measure(
    fn: Callable[..., Any], repeats: int = 1, warmup: int = 1, setup: Callable[[], Any] | None = None
) -> Timing:
    """Call ``fn`` ``warmup`` times untimed (kernel builds, caches), then ``repeats`` times
    timed; with ``setup``, each call is ``fn(setup())`` and only ``fn`` is timed."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    call = (lambda arg: fn(arg)) if setup else (lambda arg: fn())
    for _ in range(warmup):
        call(setup() if setup else None)
    watch, result = Stopwatch(), None
    for _ in range(repeats):
        arg = setup() if setup else None
        with watch:
            result = call(arg)
    timing = watch.timing()
    timing.result = result
    return timing


def write_record(path: str | os.PathLike, benchmark: str, parameters: dict, results: dict) -> dict:
    """Write ``{"benchmark", "parameters", "results", "environment"}`` (clflow.environment:
    versions, device, commit, date, load) as JSON at ``path``, atomically; returns it."""
    from clflow.environment import environment
    from clflow.fileio import atomic_write_text

    record = {"benchmark": benchmark, "parameters": parameters, "results": results, "environment": environment()}
    atomic_write_text(Path(path), json.dumps(record, indent=2, default=str) + "\n")
    return record


__all__ = ["Stopwatch", "Timing", "load_average", "measure", "write_record"]
