"""The torch bridge: zero-copy buffers on unified memory, copies otherwise, clear errors."""

import numpy as np
import pytest
import torch

from clflow.errors import InputError
from clflow.runtime.bridge import bind


def scatter_kernel(device, real="float"):
    return device.kernel("common/scatter_add.cl", "scatter_add", real)


def run_scatter(device, binding, values, index, out):
    n = index.numel()
    device.launch(
        scatter_kernel(device, "double" if values.dtype == torch.float64 else "float"),
        n,
        dict(
            values=binding.input(values),
            index=binding.input(index),
            out=binding.inout(out),
            n=np.int32(n),
            width=np.int32(1),
        ),
    )


def test_zero_copy_buffer_aliases_the_tensor_and_kernels_write_into_it(device):
    if not device.zero_copy:
        pytest.skip(f"{device.info.label} has its own memory here (a discrete device or the bridge's copy mode)")
    out = torch.zeros(4)
    with bind(device) as b:
        assert b.zero_copy
        buf = b.inout(out)
        host = buf.get_host_array(out.shape, np.float32)
        assert host.__array_interface__["data"][0] == out.data_ptr()  # the buffer is the tensor
        device.launch(
            scatter_kernel(device),
            3,
            dict(
                values=b.input(torch.tensor([1.5, 2.0, 4.0])),
                index=b.input(torch.tensor([3, 0, 3], dtype=torch.int32)),
                out=buf,
                n=np.int32(3),
                width=np.int32(1),
            ),
        )
        device.finish()
        # PoCL's CPU device wrote straight into the tensor: visible before any copy or map.
        assert out.tolist() == [2.0, 0.0, 0.0, 5.5]
    assert out.tolist() == [2.0, 0.0, 0.0, 5.5]


def test_copy_path_for_discrete_devices(device):
    out = torch.zeros(3, dtype=torch.float64)
    with bind(device) as b:
        b.zero_copy = False  # what a discrete GPU gets: copy in, run, copy back
        run_scatter(
            device, b, torch.tensor([1.0, 2.0], dtype=torch.float64), torch.tensor([2, 2], dtype=torch.int32), out
        )
    assert out.tolist() == [0.0, 0.0, 3.0]


def test_outputs_are_current_when_the_block_ends(device):
    out = torch.zeros(1000)
    values = torch.ones(100000)
    index = torch.randint(0, 1000, (100000,), dtype=torch.int32)
    with bind(device) as b:
        run_scatter(device, b, values, index, out)
    assert torch.equal(out, torch.bincount(index, minlength=1000).float())


def test_empty_tensors_are_fine(device):
    with bind(device) as b:
        b.input(torch.empty(0))
        b.output(torch.empty(0, 3, dtype=torch.float64))


@pytest.mark.parametrize(
    "tensor, message",
    [
        (torch.zeros(4, 4).t(), "not contiguous"),
        (torch.zeros(4, 4)[:, 1], "not contiguous"),
        (torch.zeros(3, dtype=torch.float16), "unsupported dtype"),
        (torch.zeros(3, device="meta"), "CPU tensors"),
        (np.zeros(3), "expected a torch.Tensor"),
    ],
)
def test_bad_tensors_are_refused(device, tensor, message):
    with bind(device) as b, pytest.raises(InputError, match=message):
        b.input(tensor)


def test_dtype_is_checked_when_asked(device):
    with bind(device) as b, pytest.raises(InputError, match="expected torch.float64"):
        b.input(torch.zeros(3), "positions", dtype=torch.float64)


def test_scratch_buffers_are_reused_once_given_back_and_the_spare_memory_is_bounded(device, monkeypatch):
    from clflow.runtime import devices

    monkeypatch.setattr(device, "_spare_scratch", [])  # the session's device: start with no spares
    with bind(device) as b:
        first = b.scratch(3000)
        second = b.scratch(3000)  # in use at the same time: a different buffer
        assert first.int_ptr != second.int_ptr
    with bind(device) as b:
        again = b.scratch(2000)  # fits a spare one (2000 <= 3000 <= 2 x 2000): reused
        assert again.int_ptr in (first.int_ptr, second.int_ptr)
        bigger = b.scratch(7000)  # no spare is large enough: a new one
        assert bigger.size >= 7000 and bigger.int_ptr not in (first.int_ptr, second.int_ptr)
        small = b.scratch(100)  # a spare 3000-byte buffer would waste more than half: a new one
        assert small.int_ptr not in (first.int_ptr, second.int_ptr)
    monkeypatch.setattr(devices, "SPARE_SCRATCH_BYTES", 5000)
    device.give_back_scratch(device.take_scratch(4000))  # keeps the newest within the bound
    assert sum(buf.size for buf in device._spare_scratch) <= 5000
    kept = list(device._spare_scratch)
    device.give_back_scratch(device.take_scratch(6000))  # too large on its own: dropped alone
    assert device._spare_scratch == kept


def test_a_device_array_lent_to_a_binding_lives_until_the_binding_finishes(device):
    """A temporary DeviceArray whose buffer a kernel takes (b.input(DeviceArray.of(...))) is
    kept by the binding until its kernels have run: on a zero-copy device its buffer is the
    array's own host memory, which torch would otherwise hand to the next tensor while the
    kernel still reads it (a rendering read another array's values that way)."""
    import gc
    import weakref

    from clflow.runtime.arrays import DeviceArray

    values = torch.arange(64, dtype=torch.float32)
    index = torch.arange(64, dtype=torch.int32)
    out = torch.zeros(64, dtype=torch.float32)
    with bind(device) as b:
        lent = DeviceArray.of(device, values)
        alive = weakref.ref(lent)
        run_scatter(device, b, lent, index, out)
        del lent
        gc.collect()
        assert alive() is not None
    gc.collect()
    assert alive() is None
    assert torch.equal(out, values)
