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

docs/benchmarks.md is generated from one record a benchmark (its current figure) in
docs/benchmarks/records/: ``python -m clflow.benchmark`` writes it (``render_page``).
"""

from __future__ import annotations

import json
import os
import re
import statistics
import textwrap
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


PAGE = Path("docs/benchmarks.md")
RECORDS = Path("docs/benchmarks/records")
# what each record of RECORDS holds; the last four may be null where the docs did not say
RECORD_FIELDS = ("benchmark", "section", "what", "command", "date", "figures", "commit", "device", "load", "target")
SECTIONS = {
    "accuracy": "Accuracy: system identification (`clflow eval sysid`) and the demos",
    "cpu": "Speed on the CPU",
    "gpu": "Speed on a GPU",
}
PAGE_WIDTH = 100
# the space between a number and its unit, kept on one line
UNBROKEN = re.compile(r"(?<=\d) (?=(?:s|ms|us|min|px|MiB|GiB|M|B|dB|deg|%)(?!\w))")

INTRODUCTION = """\
How fast and how accurate clflow is now: one entry per benchmark, its current figure with the
command that measures it, the date, the commit, the device, how busy the machine was (load
average; the 2-core hosts share their cores with other jobs at times, so a load above 2
means other work beside it) and its target where one is set. Wall-clock figures grow with
the load, CPU time much less; the last bits of an identification depend on the host's CPU.
Every earlier figure is in the history, by month:
[history/benchmarks-2026-11.md](history/benchmarks-2026-11.md) and
[history/benchmarks-2026-12.md](history/benchmarks-2026-12.md).

This page is generated from the records in `docs/benchmarks/records/` (one JSON file a
benchmark) by `python -m clflow.benchmark`; tests/test_benchmark_page.py holds the two equal.
To record a new figure, replace the fields of its record (moving the old figure to the
history), then run that command.

## How to run them

Every `clflow bench ...` command times through `clflow.benchmark.measure` (untimed warm-up,
repeats, wall and CPU time, load before and after) and takes `--json PATH`: the figures, the
parameters and the environment (versions, device, commit, date, load), e.g.
`clflow bench raster --repeat 5 --json raster.json`. `clflow eval sysid -o FOLDER` writes
`FOLDER/sysid.json` and `sysid.md` (every case's found values, ranges, losses and EPE);
`--quick` runs three cases in minutes. `clflow demo` and `clflow sweep` are timed whole.
Each entry below gives its command; `clflow --device NAME ...` runs it on another device
(docs/gpu.md).
"""


def read_records(folder: str | os.PathLike = RECORDS) -> list[dict]:
    """The benchmark records of ``folder`` (``NAME.json`` each), ordered by file name."""
    return [json.loads(path.read_text()) for path in sorted(Path(folder).glob("*.json"))]


def _wrapped(text: str, first: str, rest: str) -> str:
    """``text`` filled to ``PAGE_WIDTH``; a line is never broken between a number and its unit
    or around " - ", so no continuation line starts as a list item or with a bare unit."""
    held = UNBROKEN.sub("\N{NO-BREAK SPACE}", text.replace(" - ", "\N{NO-BREAK SPACE}-\N{NO-BREAK SPACE}"))
    filled = textwrap.fill(
        held, PAGE_WIDTH, initial_indent=first, subsequent_indent=rest, break_long_words=False, break_on_hyphens=False
    )
    return filled.replace("\N{NO-BREAK SPACE}", " ")


def _entry(record: dict) -> str:
    """One benchmark's current figure as a list item, its lines at most ``PAGE_WIDTH`` wide."""
    measured = [record["date"], record["commit"] and f"commit {record['commit']}", record["device"]]
    measured += [record["load"] and f"load: {record['load']}"]
    lines = [
        f"command: `{record['command']}`",
        "figures: " + "; ".join(f"{name}: {value}" for name, value in record["figures"].items()),
        f"target: {record['target'] or 'none set'}",
        "measured: " + "; ".join(part for part in measured if part),
    ]
    lines += [f"notes: {record['notes']}"] if record.get("notes") else []
    lines += [f"more: {record['docs']}"] if record.get("docs") else []
    lines += [f"record: `{RECORDS.as_posix()}/{record['benchmark']}.json`"]
    items = [_wrapped(f"**{record['what']}**", "- ", "  ")] + [_wrapped(line, "  - ", "    ") for line in lines]
    return "\n".join(items)


def render_page(records: list[dict]) -> str:
    """docs/benchmarks.md from ``records``: the introduction, then a section of entries for
    each of ``SECTIONS``, in the records' order."""
    parts = ["# Benchmarks\n", INTRODUCTION]
    for section, title in SECTIONS.items():
        entries = [_entry(record) for record in records if record["section"] == section]
        parts.append(f"## {title}\n\n" + "\n".join(entries) + "\n")
    return "\n".join(parts)


def write_page(root: str | os.PathLike = ".") -> Path:
    """Render the records under ``root`` into its docs/benchmarks.md; returns the page's path.
    The page is a file of the repository, not a run's output: written in place, no
    written-record beside it."""
    page = Path(root) / PAGE
    page.write_text(render_page(read_records(Path(root) / RECORDS)))
    return page


__all__ = [
    "RECORD_FIELDS",
    "SECTIONS",
    "Stopwatch",
    "Timing",
    "load_average",
    "measure",
    "read_records",
    "render_page",
    "write_page",
    "write_record",
]

if __name__ == "__main__":
    print(write_page())
