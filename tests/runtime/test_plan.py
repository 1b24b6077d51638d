"""The kernel plan's registry (clflow.runtime.plan.STAGE_KERNELS) against the sources and
against its table in docs/gpu.md."""

from __future__ import annotations

import re
from pathlib import Path

from clflow.runtime.plan import STAGE_KERNELS, KernelPlan

ROOT = Path(__file__).resolve().parents[2]
DEVICE_SHAPES = {"CPU devices": KernelPlan.of("cpu"), "GPUs": KernelPlan.of("gpu")}


def taken_by(stage: str, shape: str) -> str:
    """Which devices take ``shape`` of ``stage`` by default: "CPU devices", "GPUs", both, or
    "when asked for"."""
    takers = [name for name, plan in DEVICE_SHAPES.items() if getattr(plan, stage) == shape]
    return ", ".join(takers) or "when asked for"


def registry_rows() -> list[str]:
    """The table's rows as the registry says them: stage, shape, who takes it, and its
    kernels by source in launch order."""
    rows = []
    for stage, shapes in STAGE_KERNELS.items():
        for shape, roles in shapes.items():
            by_source: dict[str, list[str]] = {}
            for kernel in roles.values():
                by_source.setdefault(kernel.source, []).append(f"`{kernel.entry}`")
            kernels = "; ".join(f"`{source}`: {', '.join(entries)}" for source, entries in by_source.items())
            rows.append(f"| {stage} | {shape} | {taken_by(stage, shape)} | {kernels} |")
    return rows


def docs_rows() -> list[str]:
    text = (ROOT / "docs" / "gpu.md").read_text()
    table = text.split("<!-- STAGE_KERNELS -->")[1]
    return [line for line in table.splitlines() if line.startswith("| ") and not line.startswith("| stage ")]


def test_the_docs_table_is_the_registry():
    assert docs_rows() == registry_rows(), "\n".join(registry_rows())


def test_every_registered_kernel_is_in_its_source():
    for shapes in STAGE_KERNELS.values():
        for roles in shapes.values():
            for kernel in roles.values():
                source = (ROOT / "kernels_cl" / kernel.source).read_text()
                assert re.search(rf"\b{kernel.entry}\s*\(", source), kernel


def test_each_plan_has_a_shape_of_every_stage():
    for plan in DEVICE_SHAPES.values():
        for stage, shapes in STAGE_KERNELS.items():
            assert getattr(plan, stage) in shapes, (plan.kind, stage)
