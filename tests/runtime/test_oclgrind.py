"""The common kernels under oclgrind: no out-of-bounds access, no races, no uninitialised reads."""

import pytest

pytestmark = pytest.mark.oclgrind

CODE = """
import torch
from clflow.runtime import get_device
from clflow.runtime.reduction import scatter_add, sum_rows

dev = get_device()
assert dev.info.is_oclgrind, dev.info
for dtype in (torch.float32, torch.float64):
    x = torch.randn(1100, 3, dtype=dtype)          # two passes, a ragged last group
    assert torch.allclose(sum_rows(x, dev), x.double().sum(0), rtol=1e-6, atol=1e-6)
    v = torch.randn(300, 2, dtype=dtype)
    i = torch.randint(0, 5, (300,))                 # heavy contention on 5 rows
    assert torch.allclose(scatter_add(v, i, 5, dev), torch.zeros(5, 2, dtype=dtype).index_add(0, i, v), atol=1e-4)
print("checked")
"""


def test_reduction_and_atomic_add_are_clean_under_oclgrind(oclgrind):
    out, log = oclgrind(CODE)
    assert "checked" in out
    assert log.strip() == "", log
