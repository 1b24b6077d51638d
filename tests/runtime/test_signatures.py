"""Kernel calls by name (clflow.runtime.signatures): the table is the kernel's own OpenCL
signature, read from the driver; a call that does not match it is refused before anything
runs, naming the kernel and the argument."""

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from clflow.mpm.constants import kernel_defines
from clflow.runtime.arrays import DeviceArray
from clflow.runtime.signatures import SCALAR_TYPES, KernelArgument, KernelCallError

ROOT = Path(__file__).resolve().parents[2]


def key_ranges_call(device, keys, n=None):
    ranges = DeviceArray.zeros(device, (4, 2), torch.int32)
    args = {"n": np.int32(len(keys) if n is None else n), "ranges": ranges}  # not in the kernel's order
    return ranges, args | {"keys": DeviceArray.of(device, torch.tensor(keys, dtype=torch.int32), "keys")}


def test_the_table_is_the_kernels_own_signature(device):
    kernel = device.kernel("common/sort.cl", "key_ranges")
    assert device.signature(kernel).arguments == (
        KernelArgument("keys", "uint*"),
        KernelArgument("ranges", "int*"),
        KernelArgument("n", "int"),
    )


def test_the_scalars_are_declared_to_pyopencl_so_it_packs_them_itself(device):
    """Device.kernel declares each scalar argument's dtype (``real`` resolved; pointers None),
    pyopencl's fast path: packing a scalar undeclared costs 10-20 us on PoCL."""
    from clflow.runtime.signatures import KernelSignature

    kernel = device.kernel("common/sort.cl", "key_ranges")
    assert device.signature(kernel).scalar_dtypes() == [None, None, np.dtype(np.int32)]
    grid = device.kernel("mpm/grid.cl", "grid_update", "double", kernel_defines(0.0))
    dtypes = dict(zip((a.name for a in device.signature(grid).arguments), device.signature(grid).scalar_dtypes()))
    assert dtypes["dt"] == np.float64 and dtypes["nx"] == np.int32 and dtypes["grid"] is None
    assert KernelSignature("k", "float", (KernelArgument("x", "real"),)).scalar_dtypes() == [np.dtype(np.float32)]
    # declared: pyopencl packs a plain Python number itself (undeclared, PoCL refuses it)
    ranges, args = key_ranges_call(device, [0, 0, 2])
    kernel.set_args(args["keys"].buffer, ranges.buffer, 3)


def test_a_call_by_name_runs_in_the_kernels_order(device):
    ranges, args = key_ranges_call(device, [0, 0, 2, 2, 2, 3])
    device.launch(device.kernel("common/sort.cl", "key_ranges"), 6, args)
    assert ranges.read().tolist() == [[0, 2], [0, 0], [2, 5], [5, 6]]


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda a: a.pop("n"), "missing n (it takes keys, ranges, n)"),
        (lambda a: a.update(count=np.int32(3)), "unknown count"),
        (lambda a: a.update(n=3), "argument n (int) needs a sized numpy scalar, given 3"),
        (lambda a: a.update(n=np.float32(3)), "argument n (int) given a float32 scalar"),
        (lambda a: a.update(ranges=np.int32(0)), "argument ranges (int*) is a pointer, given the number 0"),
    ],
)
def test_a_call_that_does_not_match_is_refused_before_it_runs(device, change, message):
    kernel = device.kernel("common/sort.cl", "key_ranges")
    device.launch(kernel, 2, key_ranges_call(device, [1, 1])[1])  # a good call first: checked kinds are cached
    ranges, args = key_ranges_call(device, [1, 1])
    change(args)
    with pytest.raises(KernelCallError, match="kernel key_ranges: .*" + re.escape(message)):
        device.launch(device.kernel("common/sort.cl", "key_ranges"), 2, args)
    assert ranges.read().tolist() == [[0, 0]] * 4  # nothing ran


def test_an_array_of_the_wrong_kind_or_width_is_refused(device):
    _, args = key_ranges_call(device, [1, 1])
    args["ranges"] = DeviceArray.zeros(device, (4, 2), torch.float32)
    with pytest.raises(KernelCallError, match="argument ranges \\(int\\*\\) given an array of torch.float32"):
        device.launch(device.kernel("common/sort.cl", "key_ranges"), 2, args)


@pytest.mark.parametrize("real", ["float", "double"])
def test_every_mpm_kernel_builds_with_a_table_the_checks_cover(device, real):
    """Every kernel of kernels_cl/mpm (with the PIC/FLIP switch on, the widest set) exposes
    named arguments of types the call check knows: scalars, ``real``, pointers to them."""
    known = {*SCALAR_TYPES, "real"}
    for source in sorted((ROOT / "kernels_cl" / "mpm").rglob("*.cl")):
        program = device.program(str(source.relative_to(ROOT / "kernels_cl")), real, kernel_defines(0.5))
        for kernel in program.all_kernels():
            signature = device.signature(
                device.kernel(
                    str(source.relative_to(ROOT / "kernels_cl")), kernel.function_name, real, kernel_defines(0.5)
                )
            )
            names = [a.name for a in signature.arguments]
            assert len(set(names)) == len(names) and all(names), signature
            assert all(a.type_name.rstrip("*") in known for a in signature.arguments), signature


def test_a_positional_call_is_refused(device):
    ranges, args = key_ranges_call(device, [1, 1])
    with pytest.raises(KernelCallError, match="kernel key_ranges: pass its arguments by name"):
        device.launch(device.kernel("common/sort.cl", "key_ranges"), 2, [args["keys"], ranges, np.int32(2)])
