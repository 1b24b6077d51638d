"""Which kernel serves each parallel stage on a device: the one place that decides it.

CPU devices (PoCL) run best with a few work-items per core, each streaming through a
contiguous block (no barriers, no atomics), and with SIMD lanes where PoCL does not
vectorise across work-items itself; GPUs need tens of thousands of work-items and
work-groups that cooperate through local memory. A :class:`KernelPlan` names each stage's
shape, and :data:`STAGE_KERNELS` the kernels (source under kernels_cl/, entry point) that
serve each shape; docs/gpu.md ("Kernel shapes") lists the same table, and a test holds the
two together.

Every launch site asks :func:`kernel_plan` for its kernels; none tests the device type
itself. ``CLFLOW_KERNELS=gpu|cpu|auto`` forces the shapes (``auto``, the default: ``cpu`` on
CPU devices, ``gpu`` elsewhere), so CI runs the GPU shapes on PoCL. The P2G path may be asked
for (a simulator's ``p2g``, else ``CLFLOW_P2G``): the plan then records the path taken, and
the adjoint's scatter follows a private or gather P2G.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import Literal, NamedTuple

from clflow.errors import InputError

KERNELS_ENV = "CLFLOW_KERNELS"
PLAN_KINDS = ("auto", "cpu", "gpu")
PlanKind = Literal["cpu", "gpu"]
P2GMode = Literal["auto", "private", "atomic", "gather"]
P2G_MODES = ("auto", "private", "atomic", "gather")
#: Forces the P2G path of every simulator whose caller asks for "auto" (the default):
#: "private", "atomic" or "gather". CI runs the MPM suite with the GPUs' paths on PoCL this way.
P2G_ENV = "CLFLOW_P2G"


class Kernel(NamedTuple):
    """One kernel: its OpenCL source (relative to kernels_cl/) and its entry point."""

    source: str
    entry: str


def _kernels(source: str, **entries: str) -> dict[str, Kernel]:
    """Role -> Kernel for entry points of one ``source``."""
    return {role: Kernel(source, entry) for role, entry in entries.items()}


_SCAN, _SORT, _PRIVATE = "common/scan.cl", "common/sort.cl", "mpm/p2g_private.cl"
_STRESS, _STRESS_ADJOINT = "mpm/stress.cl", "mpm/adjoint/stress_adjoint.cl"
_GRID_UPDATE, _G2P = Kernel("mpm/grid.cl", "grid_update"), Kernel("mpm/g2p.cl", "g2p")

#: stage -> shape -> role -> the kernel that serves it there (roles in launch order).
STAGE_KERNELS: dict[str, dict[str, dict[str, Kernel]]] = {
    "scan": {
        "serial": _kernels(_SCAN, scan="scan_serial"),
        "workgroup": _kernels(_SCAN, block_sums="scan_block_sums", summed="scan_blocks_summed", blocks="scan_blocks"),
    },
    "sort": {
        "blocks": _kernels(_SORT, histogram="radix_histogram", scatter="radix_scatter"),
        "workgroup": _kernels(_SORT, histogram="radix_histogram_wg", scatter="radix_scatter_wg"),
    },
    "stress": {
        "simd_lanes": _kernels(
            _STRESS, svd="trial_svd_simd", models="update_stress", elastic="update_stress_elastic_simd"
        ),
        "plain": _kernels(
            _STRESS,
            svd="trial_svd",
            models="update_stress",
            elastic="update_stress_elastic",
            models_cells="update_stress_cells",  # the SVD inline, and the particles keyed by cell
            elastic_cells="update_stress_elastic_cells",
        ),
    },
    "p2g": {
        "private": {
            "p2g": Kernel(_PRIVATE, "p2g_private"),
            "grid": Kernel("mpm/grid.cl", "sum_copies_update_grid"),
            "g2p": _G2P,
        },
        "gather": {  # over blocks of cells, each particle read once; the grid update after the blocks' sums
            **_kernels("mpm/p2g_gather.cl", cells="particle_cells", p2g="p2g_blocks", grid="p2g_blocks_update"),
            "g2p": Kernel("mpm/g2p.cl", "g2p_sorted"),
        },
        "atomic": {"p2g": Kernel("mpm/p2g_atomic.cl", "p2g_atomic"), "grid": _GRID_UPDATE, "g2p": _G2P},
    },
    "adjoint_scatter": {
        "private": {
            "g2p": Kernel("mpm/adjoint/g2p_adjoint_private.cl", "g2p_adjoint_private"),
            "sum": Kernel(_PRIVATE, "sum_grid_copies"),
        },
        "gather": _kernels(  # over the forward's cell sort, which the tape keeps
            "mpm/adjoint/g2p_adjoint_gather.cl", g2p="g2p_adjoint_records", gather="g2p_adjoint_gather_update"
        ),
    },
    "stress_adjoint": {
        "simd_lanes": {
            "svd": Kernel(_STRESS, "trial_svd_simd"),
            **_kernels(_STRESS_ADJOINT, models="update_stress_adjoint", elastic="update_stress_elastic_adjoint_simd"),
        },
        "plain": {
            "svd": Kernel(_STRESS, "trial_svd"),
            **_kernels(_STRESS_ADJOINT, models="update_stress_adjoint", elastic="update_stress_elastic_adjoint"),
        },
    },
    "raster": {
        "tile_rows": _kernels(
            "splat/rasterize_tile_rows.cl", forward="rasterize_forward", backward="rasterize_backward"
        ),
        "workgroup": _kernels(
            "splat/rasterize_workgroup.cl", forward="rasterize_tiles_forward", backward="rasterize_tiles_backward"
        ),
    },
}


@dataclass(frozen=True)
class KernelPlan:
    """The shape of each parallel stage on one device; :meth:`kernel` names its kernels."""

    kind: PlanKind
    scan: Literal["serial", "workgroup"]
    sort: Literal["blocks", "workgroup"]
    p2g: Literal["private", "gather", "atomic"]
    adjoint_scatter: Literal["private", "gather"]
    raster: Literal["tile_rows", "workgroup"]
    stress: Literal["simd_lanes", "plain"]

    @property
    def stress_keys_cells(self) -> bool:
        """Whether the forward stress kernels also key the particles by cell for the gather's
        sort (the plain shape's update_stress_cells, update_stress_elastic_cells: one launch
        fewer a substep); the SIMD-lane ones leave it to particle_cells."""
        return self.p2g == "gather" and self.stress == "plain"

    @property
    def stress_adjoint(self) -> str:
        """The stress adjoint's shape: the forward stress stage's."""
        return self.stress

    @staticmethod
    def of(kind: PlanKind) -> "KernelPlan":
        if kind == "cpu":
            return KernelPlan("cpu", "serial", "blocks", "private", "private", "tile_rows", "simd_lanes")
        return KernelPlan("gpu", "workgroup", "workgroup", "gather", "gather", "workgroup", "plain")

    def with_p2g(self, requested: P2GMode = "auto") -> "KernelPlan":
        """This plan with the P2G path taken: ``requested`` unless "auto"; then $CLFLOW_P2G,
        else the plan's own (private grid copies on CPU devices, the gather over blocks of cells on GPUs).
        The private and gather paths sum in a fixed order, so runs repeat to the bit; "atomic"
        (a work-item per particle, atomic adds in no fixed order) is there to ask for. The
        adjoint's scatter takes the P2G's shape, private or gather (it has no atomic one)."""
        if requested not in P2G_MODES:
            raise InputError(f"p2g must be one of {', '.join(P2G_MODES)}, not {requested!r}")
        path = requested if requested != "auto" else forced_p2g() or self.p2g
        scatter = path if path in ("private", "gather") else self.adjoint_scatter
        return dataclasses.replace(self, p2g=path, adjoint_scatter=scatter)

    def kernel(self, stage: str, role: str) -> Kernel:
        """The kernel of ``role`` in ``stage`` (a key of STAGE_KERNELS) in this plan's shape."""
        return STAGE_KERNELS[stage][getattr(self, stage)][role]

    def describe(self) -> str:
        """One line: the plan and each stage's shape."""
        return (
            f"{self.kind} (scan {self.scan}, sort {self.sort}, P2G {self.p2g}, adjoint {self.adjoint_scatter}, "
            f"raster {self.raster}, stress {self.stress})"
        )


def forced_kind() -> str:
    """$CLFLOW_KERNELS, checked: "auto", "cpu" or "gpu"."""
    value = os.environ.get(KERNELS_ENV, "").strip().lower() or "auto"
    if value not in PLAN_KINDS:
        raise InputError(f"${KERNELS_ENV} must be one of {', '.join(PLAN_KINDS)}, got {value!r}")
    return value


def forced_p2g() -> str | None:
    """$CLFLOW_P2G, checked: "private", "atomic" or "gather"; None when unset or "auto"."""
    value = os.environ.get(P2G_ENV, "").strip().lower()
    if value and value not in P2G_MODES:
        raise InputError(f"${P2G_ENV} must be one of {', '.join(P2G_MODES)}, got {value!r}")
    return value if value and value != "auto" else None


def kernel_plan(device, p2g: P2GMode = "auto") -> KernelPlan:
    """The plan of ``device`` (a clflow Device) with the P2G path ``p2g`` asks for: see
    :func:`plan_for_type` and :meth:`KernelPlan.with_p2g`."""
    return plan_for_type(device.info.type, p2g)


def plan_for_type(device_type: str, p2g: P2GMode = "auto") -> KernelPlan:
    """The plan of a device of OpenCL type ``device_type`` ("CPU", "GPU", ...):
    $CLFLOW_KERNELS when it is "cpu" or "gpu", else "cpu" on CPU devices and "gpu" on every
    other kind; its P2G path as :meth:`KernelPlan.with_p2g` takes it."""
    kind = forced_kind()
    if kind == "auto":
        kind = "cpu" if device_type == "CPU" else "gpu"
    return KernelPlan.of(kind).with_p2g(p2g)
