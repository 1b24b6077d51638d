"""Which shape of each parallel stage a device runs: the one place that decides it.

CPU devices (PoCL) run best with a few work-items per core, each streaming through a
contiguous block (no barriers, no atomics); GPUs need tens of thousands of work-items and
work-groups that cooperate through local memory. The stages that differ:

============== ===================================== ===========================================
stage          ``cpu`` shape                         ``gpu`` shape
============== ===================================== ===========================================
scan           one work-item walks the array         reduce-then-scan in work-groups
radix sort     64 work-items, each a block           work-groups of 256, a digit's rank in local memory
particle sort  (none: P2G needs no sort)             counting sort by cell, one pass
P2G            private grid copies                   gather per node over particles sorted by cell
adjoint G2P    private grid copies                   gather per node over particles sorted by cell
raster         a work-item per 16x16 tile            a work-group per tile, entries staged in local memory
============== ===================================== ===========================================

Every launch site asks :func:`kernel_plan`; none tests the device type itself.
``CLFLOW_KERNELS=gpu|cpu|auto`` forces the choice (``auto``, the default: ``cpu`` on CPU
devices, ``gpu`` elsewhere), so CI runs the GPU shapes on PoCL. ``CLFLOW_P2G`` still
overrides the forward P2G path alone (clflow.mpm.substep.p2g_path).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

from clflow.errors import InputError

KERNELS_ENV = "CLFLOW_KERNELS"
PLAN_KINDS = ("auto", "cpu", "gpu")
PlanKind = Literal["cpu", "gpu"]


@dataclass(frozen=True)
class KernelPlan:
    """The shape of each parallel stage on one device (see the module's table)."""

    kind: PlanKind
    scan: Literal["serial", "workgroup"]
    sort: Literal["blocks", "workgroup"]
    p2g: Literal["private", "gather"]
    adjoint_scatter: Literal["private", "gather"]
    raster: Literal["tile_rows", "workgroup"]

    @staticmethod
    def of(kind: PlanKind) -> "KernelPlan":
        if kind == "cpu":
            return KernelPlan("cpu", "serial", "blocks", "private", "private", "tile_rows")
        return KernelPlan("gpu", "workgroup", "workgroup", "gather", "gather", "workgroup")

    def describe(self) -> str:
        """One line: the plan and each stage's shape."""
        return (
            f"{self.kind} (scan {self.scan}, sort {self.sort}, P2G {self.p2g}, adjoint {self.adjoint_scatter}, "
            f"raster {self.raster})"
        )


def forced_kind() -> str:
    """$CLFLOW_KERNELS, checked: "auto", "cpu" or "gpu"."""
    value = os.environ.get(KERNELS_ENV, "").strip().lower() or "auto"
    if value not in PLAN_KINDS:
        raise InputError(f"${KERNELS_ENV} must be one of {', '.join(PLAN_KINDS)}, got {value!r}")
    return value


def kernel_plan(device) -> KernelPlan:
    """The plan of ``device`` (a clflow Device): see :func:`plan_for_type`."""
    return plan_for_type(device.info.type)


def plan_for_type(device_type: str) -> KernelPlan:
    """The plan of a device of OpenCL type ``device_type`` ("CPU", "GPU", ...):
    $CLFLOW_KERNELS when it is "cpu" or "gpu", else "cpu" on CPU devices and "gpu" on every
    other kind."""
    kind = forced_kind()
    if kind == "auto":
        kind = "cpu" if device_type == "CPU" else "gpu"
    return KernelPlan.of(kind)
