"""Deterministic column sums and atomic scatter-add against torch references."""

import math

import pytest
import torch

from clflow.errors import InputError
from clflow.runtime.reduction import REDUCE_WG, ROWS_PER_ITEM, column_sum, scatter_add, sum_rows


def fixed_order_reference(x: torch.Tensor) -> torch.Tensor:
    """Pure-torch float64 emulation of the kernels' documented summation order."""
    data = x.double()
    chunk = REDUCE_WG * ROWS_PER_ITEM
    while True:
        rows, k = data.shape
        groups = math.ceil(rows / chunk)
        padded = torch.zeros(groups * chunk, k, dtype=torch.float64)
        padded[:rows] = data
        blocks = padded.reshape(groups, ROWS_PER_ITEM, REDUCE_WG, k)  # row = g*chunk + j*WG + l
        acc = torch.zeros(groups, REDUCE_WG, k, dtype=torch.float64)
        for j in range(ROWS_PER_ITEM):
            acc = acc + blocks[:, j]
        while acc.shape[1] > 1:
            half = acc.shape[1] // 2
            acc = acc[:, :half] + acc[:, half:]
        data = acc[:, 0]
        if groups == 1:
            return data[0]


@pytest.mark.parametrize("n", [1, 63, 64, 1024, 1025, 70001])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sum_rows_equals_the_fixed_order_reference_bit_for_bit(device, n, dtype):
    x = torch.randn(n, 3, dtype=dtype, generator=torch.Generator().manual_seed(n))
    got = sum_rows(x, device)
    assert got.dtype == torch.float64 and got.shape == (3,)
    assert torch.equal(got, fixed_order_reference(x))
    torch.testing.assert_close(got, x.double().sum(0), rtol=1e-12, atol=1e-12)


def test_sum_rows_three_passes_and_bit_identical_repeats(device):
    x = torch.rand(1_100_000, 2, generator=torch.Generator().manual_seed(1))  # 1075 groups -> 2 -> 1
    runs = [sum_rows(x, device) for _ in range(3)]
    assert all(torch.equal(runs[0], r) for r in runs[1:])
    assert torch.equal(runs[0], fixed_order_reference(x))


def test_sum_rows_of_integers_is_exact(device):
    x = torch.randint(-1000, 1000, (5000, 4)).float()
    assert torch.equal(sum_rows(x, device), x.double().sum(0))


def test_sum_rows_edge_shapes_and_errors(device):
    assert torch.equal(sum_rows(torch.zeros(0, 3), device), torch.zeros(3, dtype=torch.float64))
    assert sum_rows(torch.zeros(5, 0), device).shape == (0,)
    with pytest.raises(InputError, match="2-D"):
        sum_rows(torch.zeros(5), device)
    with pytest.raises(InputError, match="float32 or float64"):
        sum_rows(torch.zeros(5, 2, dtype=torch.int32), device)


def test_column_sum_is_a_checked_torch_op(device):
    x = torch.randn(300, 4, dtype=torch.float64, requires_grad=True)
    torch.library.opcheck(column_sum, (x,))
    assert torch.autograd.gradcheck(column_sum, (x,))
    (column_sum(x) * torch.arange(4.0, dtype=torch.float64)).sum().backward()
    assert torch.equal(x.grad, torch.arange(4.0, dtype=torch.float64).expand(300, 4))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_scatter_add_matches_index_add(device, dtype):
    gen = torch.Generator().manual_seed(0)
    values = torch.randn(20000, 3, dtype=dtype, generator=gen)
    index = torch.randint(0, 50, (20000,), generator=gen)
    expected = torch.zeros(50, 3, dtype=torch.float64).index_add_(0, index, values.double())
    tol = 1e-12 if dtype == torch.float64 else 1e-3
    torch.testing.assert_close(scatter_add(values, index, 50, device).double(), expected, rtol=tol, atol=tol)


def test_scatter_add_of_integers_is_exact_despite_contention(device):
    values = torch.ones(50000)
    index = torch.zeros(50000, dtype=torch.int64)  # every work-item hits one address
    assert scatter_add(values, index, 1, device).item() == 50000.0


def test_scatter_add_rejects_bad_indices(device):
    with pytest.raises(InputError, match="out of range"):
        scatter_add(torch.ones(3), torch.tensor([0, 5, 1]), 4, device)
    with pytest.raises(InputError, match="disagree"):
        scatter_add(torch.ones(3), torch.tensor([0, 1]), 4, device)
