"""Where a device's time goes: every kernel launch's device time from OpenCL profiling
events, summed per kernel, and the host's time and launch count per step (a substep, an
adjoint substep, a rasteriser call).

    profile = device.start_profile()      # a profiling queue from here on
    ...                                   # launches are recorded by Device.launch
    report = device.stop_profile()        # waits for the device, returns the summary dict
    print(format_profile(report))

``clflow bench ... --profile`` and ``clflow --profile FILE COMMAND`` use it.
"""

from __future__ import annotations

import time
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass, field

from clflow.runtime.program_cache import ProgramBuilds

PENDING_EVENTS = 4096  # events held before the oldest half are waited for and summed


@dataclass
class StepTotals:
    """Host seconds spent enqueuing one kind of step, its count and the launches it made."""

    count: int = 0
    host_s: float = 0.0
    launches: int = 0


@dataclass
class KernelProfile:
    """Launches and device seconds per kernel name, :class:`StepTotals` per step kind, and the
    programs built meanwhile."""

    kernels: dict[str, list] = field(default_factory=dict)  # name -> [launches, device seconds]
    steps: dict[str, StepTotals] = field(default_factory=dict)
    launches: int = 0
    builds: ProgramBuilds = field(default_factory=ProgramBuilds)
    started: float = field(default_factory=time.perf_counter)
    _pending: list = field(default_factory=list)

    def record(self, name: str, event) -> None:
        """A launch of kernel ``name`` whose profiling ``event`` completes later."""
        self.launches += 1
        self._pending.append((name, event))
        if len(self._pending) >= PENDING_EVENTS:
            self._collect(PENDING_EVENTS // 2)

    def _collect(self, count: int | None = None) -> None:
        """Wait for the oldest ``count`` pending events (all by default) and add their times."""
        done = self._pending[:count] if count is not None else self._pending
        self._pending = self._pending[len(done) :]
        for name, event in done:
            event.wait()
            seconds = (event.profile.end - event.profile.start) * 1e-9
            totals = self.kernels.setdefault(name, [0, 0.0])
            totals[0] += 1
            totals[1] += seconds

    @contextmanager
    def step(self, kind: str):
        """Count the block as one step of ``kind``: its host seconds and the launches it made."""
        launches, started = self.launches, time.perf_counter()
        try:
            yield
        finally:
            totals = self.steps.setdefault(kind, StepTotals())
            totals.count += 1
            totals.host_s += time.perf_counter() - started
            totals.launches += self.launches - launches

    def summary(self) -> dict:
        """The profile so far, JSON-ready: per kernel (by device time, largest first) launches,
        device seconds and share; the totals; per step kind the host seconds and launches per
        step. Waits for the pending events."""
        self._collect()
        device_s = sum(seconds for _, seconds in self.kernels.values())
        kernels = [
            {
                "kernel": name,
                "launches": launches,
                "device_s": seconds,
                "share": seconds / device_s if device_s else 0.0,
            }
            for name, (launches, seconds) in sorted(self.kernels.items(), key=lambda item: -item[1][1])
        ]
        steps = {
            kind: {
                "count": s.count,
                "host_s_per_step": s.host_s / s.count,
                "launches_per_step": s.launches / s.count,
            }
            for kind, s in self.steps.items()
            if s.count
        }
        wall_s = time.perf_counter() - self.started
        return {
            "kernels": kernels,
            "launches": self.launches,
            "device_s": device_s,
            "wall_s": wall_s,
            "steps": steps,
            "builds": asdict(self.builds),
        }


def format_profile(report: dict, top: int = 12) -> str:
    """The summary of :meth:`KernelProfile.summary` as a table of the ``top`` kernels."""
    lines = [
        f"kernel profile: {report['launches']:,} launches, {report['device_s']:.3f} s of device time "
        f"in {report['wall_s']:.2f} s of wall time",
        f"  {'kernel':34s} {'launches':>9s} {'device s':>10s} {'each us':>9s} {'share':>6s}",
    ]
    for row in report["kernels"][:top]:
        each = row["device_s"] / row["launches"] * 1e6
        lines.append(
            f"  {row['kernel']:34s} {row['launches']:9,d} {row['device_s']:10.4f} {each:9.1f} {row['share']:6.1%}"
        )
    if len(report["kernels"]) > top:
        rest = report["kernels"][top:]
        lines.append(f"  ({len(rest)} more kernels: {sum(r['share'] for r in rest):.1%})")
    builds = report.get("builds") or {}
    if builds.get("compiled") or builds.get("loaded"):
        lines.append(
            f"  programs: {builds['compiled']} compiled ({builds['compile_s']:.2f} s), {builds['loaded']} loaded "
            f"from the program cache ({builds['load_s']:.2f} s)"
        )
    for kind, step in report["steps"].items():
        lines.append(
            f"  per {kind}: {step['launches_per_step']:.1f} launches, {step['host_s_per_step'] * 1e6:.0f} us of host "
            f"time to enqueue ({step['count']:,} steps)"
        )
    return "\n".join(lines)


_NOT_PROFILED = nullcontext()


def profiled_step(device, kind: str):
    """A context that counts a step of ``kind`` in ``device``'s profile when one is running
    (and costs nothing measurable when none is)."""
    profile = device.profile
    return _NOT_PROFILED if profile is None else profile.step(kind)
