"""Scans and sorts (clflow.runtime.sort) in both shapes of the plan (clflow.runtime.plan),
against torch: exact, stable, the same bits run after run, including sizes at and across
the work-group shape's block edges and both forms of its scan."""

import pytest
import torch

from clflow.runtime.arrays import DeviceArray
from clflow.runtime.plan import KernelPlan, kernel_plan
from clflow.runtime.sort import SCAN_BLOCK, SCAN_SUMMED_BLOCKS, scan_exclusive, sort_by_key, sort_pairs


def device_scan(device, values: torch.Tensor, in_place: bool = False) -> torch.Tensor:
    n = values.shape[0]
    out = DeviceArray.of(device, torch.cat([values, torch.zeros(1, dtype=torch.int32)]))
    src = out if in_place else DeviceArray.of(device, values if n else torch.zeros(1, dtype=torch.int32))
    scan_exclusive(device, src, out, n)
    return out.read()


def expected_scan(values: torch.Tensor) -> torch.Tensor:
    return torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(values.to(torch.int64), 0)]).to(torch.int32)


@pytest.mark.parametrize("n", [0, 1, 7, SCAN_BLOCK - 1, SCAN_BLOCK, SCAN_BLOCK + 1, 300_001])
def test_scan_is_exact(device, plan_kind, n):
    values = torch.randint(0, 50, (n,), generator=torch.Generator().manual_seed(n), dtype=torch.int32)
    assert torch.equal(device_scan(device, values), expected_scan(values))
    assert torch.equal(device_scan(device, values, in_place=True), expected_scan(values))


@pytest.mark.parametrize("n", [SCAN_BLOCK * SCAN_SUMMED_BLOCKS, SCAN_BLOCK * SCAN_SUMMED_BLOCKS + 3])
def test_the_work_group_scan_at_the_edge_of_its_two_launch_form(device, monkeypatch, n):
    """The most blocks whose work-groups add the sums before them themselves, and one more:
    then the block sums are scanned by the work-group scan too."""
    monkeypatch.setenv("CLFLOW_KERNELS", "gpu")
    values = torch.randint(0, 3, (n,), generator=torch.Generator().manual_seed(1), dtype=torch.int32)
    assert torch.equal(device_scan(device, values, in_place=True), expected_scan(values))


@pytest.mark.parametrize("bits,n", [(32, 5000), (10, 3000), (3, 1000), (5, 70_000), (32, 0), (17, 1)])
def test_radix_sort_is_stable_and_matches_torch(device, plan_kind, bits, n):
    g = torch.Generator().manual_seed(bits * 7 + n)
    keys = torch.randint(0, 2**bits if bits < 31 else 2**31 - 1, (n,), generator=g, dtype=torch.int64)
    if bits == 32 and n:  # the top bit too (keys are read as uint32)
        keys[::3] |= 1 << 31
    keys = keys.to(torch.int64) & 0xFFFFFFFF
    values = torch.arange(n, dtype=torch.int32)
    sorted_keys, sorted_values = sort_pairs(keys.to(torch.uint32).view(torch.int32), values, key_bits=bits)
    expected = torch.sort(keys, stable=True)
    assert torch.equal(sorted_keys.view(torch.uint32).to(torch.int64), expected.values)
    assert torch.equal(sorted_values.to(torch.int64), expected.indices)


@pytest.mark.parametrize("n,n_keys", [(0, 5), (1, 1), (5000, 64), (40_000, 9000), (3000, 100_000)])
def test_counting_sort_orders_each_key_by_index(device, plan_kind, n, n_keys):
    """Many equal keys (integer atomics hand out their ranks in no fixed order): the runs come
    out in index order, the same as a stable sort, twice."""
    keys = torch.randint(0, n_keys, (n,), generator=torch.Generator().manual_seed(n), dtype=torch.int32)
    expected = torch.sort(keys.to(torch.int64), stable=True).indices
    starts = torch.cat(
        [torch.zeros(1, dtype=torch.int64), torch.cumsum(torch.bincount(keys.long(), minlength=n_keys), 0)]
    )
    for _ in range(2):
        order, got_starts = sort_by_key(keys, n_keys)
        assert torch.equal(order.to(torch.int64), expected)
        assert torch.equal(got_starts.to(torch.int64), starts)


def test_the_plan_is_chosen_per_device_and_forcible(device, monkeypatch):
    monkeypatch.delenv("CLFLOW_KERNELS", raising=False)
    expected = "cpu" if device.info.type == "CPU" else "gpu"
    assert kernel_plan(device) == KernelPlan.of(expected)
    monkeypatch.setenv("CLFLOW_KERNELS", "gpu")
    assert kernel_plan(device).scan == "workgroup" and kernel_plan(device).p2g == "gather"
    monkeypatch.setenv("CLFLOW_KERNELS", "cpu")
    assert kernel_plan(device).sort == "blocks" and kernel_plan(device).adjoint_scatter == "private"
    monkeypatch.setenv("CLFLOW_KERNELS", "fast")
    from clflow.errors import InputError

    with pytest.raises(InputError, match="CLFLOW_KERNELS must be one of auto, cpu, gpu"):
        kernel_plan(device)


def test_scan_rejects_nothing_silently_at_the_int32_edge(device, plan_kind):
    """Sums stay int32 (the callers bound their totals first): a total of 2^31 - 1 is exact."""
    values = torch.tensor([2**30, 2**30 - 1, 0], dtype=torch.int32)
    assert device_scan(device, values).tolist() == [0, 2**30, 2**31 - 1, 2**31 - 1]
