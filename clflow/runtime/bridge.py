"""Torch CPU tensors as OpenCL buffers for the kernels of one call.

On devices that share memory with the host (``device.zero_copy``: CPU devices such as PoCL,
integrated GPUs) a buffer is created with ``USE_HOST_PTR`` over the tensor's own storage: no
copy, kernels read and write the tensor. On discrete GPUs (and in the bridge's copy mode)
inputs are copied in and outputs copied back, and the bytes are counted in
``device.transfers``. Either way the tensors stay referenced until the queue has finished::

    with bind(device) as b:
        x_buf = b.input(x)            # read by kernels
        out_buf = b.output(out)       # written by kernels
        device.launch(kernel, n, {"x": x_buf, "out": out_buf, "n": np.int32(n)})
    # here every kernel has finished and `out` holds the result

Tensors must be contiguous CPU tensors of a supported dtype: anything else is an
:class:`~clflow.errors.InputError`, never a silent copy or reinterpretation. State that
lives across calls (the simulator's) is a :class:`~clflow.runtime.arrays.DeviceArray`
instead; ``input``/``output``/``inout`` pass one through as its buffer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.arrays import DeviceArray

if TYPE_CHECKING:
    from clflow.runtime.devices import Device

SUPPORTED_DTYPES = (torch.float32, torch.float64, torch.int32, torch.int64, torch.uint8, torch.int8)


def check_tensor(t: torch.Tensor, what: str, dtype: torch.dtype | None = None) -> None:
    """Raise :class:`InputError` unless ``t`` can alias an OpenCL buffer as it is."""
    if not isinstance(t, torch.Tensor):
        raise InputError(f"{what}: expected a torch.Tensor, got {type(t).__name__}")
    if t.device.type != "cpu":
        raise InputError(f"{what}: tensor is on {t.device}; clflow takes CPU tensors")
    if dtype is not None and t.dtype != dtype:
        raise InputError(f"{what}: dtype {t.dtype}, expected {dtype}")
    if t.dtype not in SUPPORTED_DTYPES:
        raise InputError(f"{what}: unsupported dtype {t.dtype}")
    if not t.is_contiguous():
        raise InputError(f"{what}: tensor of shape {tuple(t.shape)} is not contiguous; pass t.contiguous()")


class TensorBinding:
    """Context manager that lends torch tensors to OpenCL kernels (see module docstring)."""

    def __init__(self, device: "Device"):
        import pyopencl as cl

        self._cl = cl
        self.device = device
        self.zero_copy = device.zero_copy
        self._keep: list[object] = []  # tensors, arrays and buffers alive until finish
        self._readback: list[tuple[object, np.ndarray]] = []  # (buffer, host array) to sync
        self._scratch: list[object] = []  # the device's reusable scratch buffers, given back at finish
        self._copies: list[tuple[object, np.ndarray]] = []  # (device buffer, host array) to copy at finish

    def __enter__(self) -> "TensorBinding":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.finish()

    def _buffer(self, t: torch.Tensor | DeviceArray, what: str, dtype, readable: bool, writable: bool):
        if isinstance(t, DeviceArray):
            if dtype is not None and t.dtype != dtype:
                raise InputError(f"{what}: dtype {t.dtype}, expected {dtype}")
            if writable:
                t.device_wrote()
            self._keep.append(t)  # a temporary array (its zero-copy host memory) lives until finish
            return t.buffer
        check_tensor(t, what, dtype)
        cl, mf = self._cl, self._cl.mem_flags
        access = mf.READ_WRITE if (readable and writable) else (mf.READ_ONLY if readable else mf.WRITE_ONLY)
        if t.numel() == 0:  # OpenCL has no empty buffers; kernels never touch this one
            buf = cl.Buffer(self.device.context, mf.READ_WRITE, 16)
            self._keep.append(buf)
            return buf
        host = t.detach().numpy()
        if self.zero_copy:
            buf = cl.Buffer(self.device.context, access | mf.USE_HOST_PTR, hostbuf=host)
        elif readable:
            buf = cl.Buffer(self.device.context, access | mf.COPY_HOST_PTR, hostbuf=host)
            self.device.transfers.count(to_device=host.nbytes)
        else:
            buf = cl.Buffer(self.device.context, access, host.nbytes)
        self._keep.extend((t, host, buf))
        if writable:
            self._readback.append((buf, host))
        return buf

    def input(self, t: torch.Tensor, what: str = "input", dtype: torch.dtype | None = None):
        """Buffer that kernels only read."""
        return self._buffer(t, what, dtype, readable=True, writable=False)

    def output(self, t: torch.Tensor, what: str = "output", dtype: torch.dtype | None = None):
        """Buffer that kernels only write (its old contents are not copied to the device)."""
        return self._buffer(t, what, dtype, readable=False, writable=True)

    def inout(self, t: torch.Tensor, what: str = "tensor", dtype: torch.dtype | None = None):
        """Buffer that kernels read and write."""
        return self._buffer(t, what, dtype, readable=True, writable=True)

    def scratch(self, nbytes: int):
        """Device-only buffer of ``nbytes`` (at least 16) for intermediate results."""
        mf, size = self._cl.mem_flags, max(16, int(nbytes))
        if self.device.info.is_oclgrind:
            # oclgrind's uninitialised-value check keeps flagging a buffer the host never
            # wrote, even after a kernel wrote it: give it host-written contents there.
            buf = self._cl.Buffer(
                self.device.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.zeros(size, np.uint8)
            )
            self._keep.append(buf)
        else:
            buf = self.device.take_scratch(size)
            self._scratch.append(buf)
        return buf

    def read_element(self, buf, index: int, dtype) -> int | float:
        """Element ``index`` of device buffer ``buf`` read as numpy ``dtype`` (waits for the
        queue; e.g. a count the host needs to size the next step)."""
        out = np.empty(1, dtype)
        self._cl.enqueue_copy(self.device.queue, out, buf, src_offset=index * out.itemsize, is_blocking=True)
        self.device.queue_drained()
        self.device.transfers.count(to_host=out.nbytes)
        return out[0].item()

    def copy_to(self, t: torch.Tensor, buf) -> None:
        """Fill tensor ``t`` (contiguous, CPU) from the start of device buffer ``buf`` when the
        binding finishes (a scratch buffer's result the host keeps)."""
        check_tensor(t, "copy_to")
        if t.numel() == 0:
            return
        host = t.numpy()
        self._keep.extend((t, host))
        self._copies.append((buf, host))

    def finish(self) -> None:
        """Bring written tensors up to date, wait for the queue, release the references."""
        cl, queue = self._cl, self.device.queue
        for buf, host in self._copies:
            cl.enqueue_copy(queue, host, buf, is_blocking=False)
            self.device.transfers.count(to_host=host.nbytes)
        self._copies.clear()
        for buf, host in self._readback:
            if self.zero_copy:
                # Map/unmap is the OpenCL way to make a USE_HOST_PTR buffer's host view
                # current; on shared memory it copies nothing.
                mapped, _ = cl.enqueue_map_buffer(
                    queue, buf, cl.map_flags.READ, 0, host.shape, host.dtype, is_blocking=True
                )
                mapped.base.release(queue)
            else:
                cl.enqueue_copy(queue, host, buf)
                self.device.transfers.count(to_host=host.nbytes)
        self.device.finish()
        self._keep.clear()
        self._readback.clear()
        for buf in self._scratch:
            self.device.give_back_scratch(buf)
        self._scratch.clear()


def bind(device: "Device") -> TensorBinding:
    """A :class:`TensorBinding` for torch tensors on ``device`` (``with bind(device) as b:``)."""
    return TensorBinding(device)
