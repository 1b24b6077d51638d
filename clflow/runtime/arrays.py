"""Arrays that stay in a device's memory across kernel launches, and the bytes the bridge copies.

A :class:`DeviceArray` is shaped and typed like a torch tensor but lives on an OpenCL device
(``device.launch`` takes it as a kernel argument directly). The host touches it only when
asked: ``write`` (host -> device), ``read`` (device -> host), ``host_view`` (the array as a
tensor to inspect or edit). How that costs depends on the device's memory:

* zero-copy (``device.zero_copy``: a CPU device such as PoCL, an integrated GPU): the array
  is a torch tensor and its buffer is created over that tensor's memory once
  (``USE_HOST_PTR``); ``host_view`` is the tensor itself, nothing is ever copied;
* separate memory (a discrete GPU, or any device in the bridge's copy mode,
  ``CLFLOW_BRIDGE=copy``): the buffer is device memory; ``write`` and ``read`` copy, and
  ``host_view`` keeps a host mirror whose in-place edits :meth:`DeviceArray.push_host_edits`
  sends back (torch's version counter tells whether the mirror was edited).

Every copy between host and device memory, here and in :class:`~clflow.runtime.bridge.TensorBinding`,
is counted in the device's :class:`~clflow.runtime.devices.Transfers`::

    mark = device.transfers.mark()
    ...                                  # kernels, reads, writes
    moved = device.transfers.since(mark)  # Transfers: to_device, to_host (bytes)

Tensors on another torch device (CUDA, ...) are accepted by ``write`` and copied through
the host (counted too, as bytes to the host): OpenCL and torch share no memory.
"""

from __future__ import annotations

from dataclasses import fields, is_dataclass, replace
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch

from clflow.errors import InputError
from clflow.runtime.binding import Fill

if TYPE_CHECKING:
    from clflow.runtime.devices import Device

ARRAY_DTYPES = (torch.float32, torch.float64, torch.int32, torch.int64, torch.uint8, torch.int8)
_REALS = {torch.float32: ("float", np.float32), torch.float64: ("double", np.float64)}


def real_of(dtype: torch.dtype, what: str = "tensor") -> str:
    """The kernels' ``real`` type ("float"/"double", Device.kernel) of a torch dtype."""
    return _real(dtype, what)[0]


def numpy_real(dtype: torch.dtype, what: str = "tensor") -> type:
    """The numpy scalar type (np.float32/np.float64) of the kernels' ``real`` kernel arguments."""
    return _real(dtype, what)[1]


def _real(dtype: torch.dtype, what: str):
    try:
        return _REALS[dtype]
    except KeyError:
        raise InputError(f"{what}: dtype {dtype} not supported; use float32 or float64") from None


def origin_device(*tensors, what: str = "inputs") -> torch.device:
    """The torch device of the given tensors (None entries and non-tensors skipped; CPU if
    none): where an op's results go. InputError when they are on different devices."""
    found = {t.device for t in tensors if isinstance(t, torch.Tensor)}
    if len(found) > 1:
        raise InputError(f"{what} are on different torch devices ({', '.join(sorted(map(str, found)))}); use one")
    return found.pop() if found else torch.device("cpu")


def to_cpu(t, device: "Device"):
    """Tensor ``t`` on the host, differentiably (autograd carries gradients back to its torch
    device); a copy from another torch device is counted in ``device.transfers``. Anything
    else (None, numbers) is returned as it is."""
    if not isinstance(t, torch.Tensor) or t.device.type == "cpu":
        return t
    if t.device.type == "meta":
        raise InputError("a tensor on the meta device has no data")
    device.transfers.count(to_host=t.numel() * t.element_size())
    return t.to("cpu")


def to_origin(t, origin: torch.device, device: "Device"):
    """Host tensor ``t`` moved to the torch device ``origin`` (differentiably, counted), the
    inverse of :func:`to_cpu`; anything else is returned as it is."""
    if not isinstance(t, torch.Tensor) or origin.type == "cpu":
        return t
    device.transfers.count(to_device=t.numel() * t.element_size())
    return t.to(origin)


def host_tensor(t: torch.Tensor, device: "Device", what: str) -> torch.Tensor:
    """``t``'s values as a contiguous CPU tensor (a tensor on another torch device is copied
    to the host once, counted as by :func:`to_cpu`)."""
    if not isinstance(t, torch.Tensor):
        raise InputError(f"{what}: expected a torch.Tensor, got {type(t).__name__}")
    return to_cpu(t.detach(), device).contiguous()


class DeviceArray:
    """An array of ``shape`` and torch ``dtype`` in ``device``'s memory (see the module docstring).

    Create with :meth:`empty`, :meth:`zeros` or :meth:`of` (a tensor's values); ``buffer`` is
    the OpenCL buffer kernels take; ``aliased`` says whether it is a host tensor's memory.
    """

    __slots__ = ("device", "shape", "dtype", "nbytes", "buffer", "host", "_mirror", "_mirror_version", "__weakref__")

    def __init__(self, device: "Device", shape: Sequence[int], dtype: torch.dtype, host: torch.Tensor | None = None):
        import pyopencl as cl

        if dtype not in ARRAY_DTYPES:
            raise InputError(f"device array: unsupported dtype {dtype}")
        self.device, self.shape, self.dtype = device, tuple(int(s) for s in shape), dtype
        self.nbytes = int(np.prod(self.shape, dtype=np.int64)) * torch.empty((), dtype=dtype).element_size()
        mf = cl.mem_flags
        self.host: torch.Tensor | None = None
        self._mirror: torch.Tensor | None = None  # copy mode: the host view last handed out
        self._mirror_version = -1
        if self.nbytes == 0:  # OpenCL has no empty buffers; kernels never touch this one
            self.buffer = cl.Buffer(device.context, mf.READ_WRITE, 16)
        elif device.zero_copy:
            self.host = torch.empty(self.shape, dtype=dtype) if host is None else host
            self.buffer = cl.Buffer(device.context, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=self.host.numpy())
        elif device.info.is_oclgrind:
            # oclgrind's uninitialised-value check flags a buffer the host never wrote, even
            # after a kernel wrote it: give it host-written contents there
            zeros = np.zeros(self.nbytes, np.uint8)
            self.buffer = cl.Buffer(device.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=zeros)
        else:
            self.buffer = cl.Buffer(device.context, mf.READ_WRITE, self.nbytes)

    # -- construction ---------------------------------------------------------------------

    @classmethod
    def empty(cls, device: "Device", shape: Sequence[int], dtype: torch.dtype) -> "DeviceArray":
        """Uninitialised contents."""
        return cls(device, shape, dtype)

    @classmethod
    def zeros(cls, device: "Device", shape: Sequence[int], dtype: torch.dtype) -> "DeviceArray":
        return cls(device, shape, dtype).zero_()

    @classmethod
    def of(cls, device: "Device", t: torch.Tensor, what: str = "tensor") -> "DeviceArray":
        """A new array holding the values of tensor ``t`` (any torch device)."""
        t = host_tensor(t, device, what)
        array = cls(device, t.shape, t.dtype)
        array.write(t, what)
        return array

    @classmethod
    def alias(cls, device: "Device", t: torch.Tensor, what: str = "tensor") -> "DeviceArray":
        """Tensor ``t``'s values for kernels that only read them: on a zero-copy device the
        tensor's own memory (no copy; ``t`` must then not change while kernels use it), else
        an upload as by :meth:`of`."""
        t = host_tensor(t, device, what)
        if not device.zero_copy or not t.numel() or t.dtype not in ARRAY_DTYPES:
            return cls.of(device, t, what)
        return cls(device, t.shape, t.dtype, host=t)

    def empty_like(self) -> "DeviceArray":
        return DeviceArray(self.device, self.shape, self.dtype)

    def clone(self) -> "DeviceArray":
        return self.empty_like().copy_(self)

    def __repr__(self) -> str:
        return f"DeviceArray({list(self.shape)}, {self.dtype}, {self.device.info.name!r})"

    def numel(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def aliased(self) -> bool:
        """Whether the array is a host tensor's memory (a zero-copy device)."""
        return self.host is not None

    # -- device-side operations (queued, no host copy) ------------------------------------

    def zero_(self) -> "DeviceArray":
        """Fill with zero bytes on the device."""
        import pyopencl as cl

        recording = self.device.recorder  # inside Device.recording: a step to replay
        if recording is not None:
            recording.steps.append(Fill(self))
            return self
        if self.nbytes:
            self.device.keep_until_done([a.host for a in (self,) if a.host is not None])
            cl.enqueue_fill_buffer(self.device.queue, self.buffer, np.zeros(1, np.uint8), 0, self.nbytes)
            self._mirror = None
        return self

    def copy_(self, other: "DeviceArray") -> "DeviceArray":
        """Copy ``other`` (same shape and dtype, same device) into this array, on the device."""
        import pyopencl as cl

        if other.shape != self.shape or other.dtype != self.dtype:
            raise InputError(f"copy_: {other!r} into {self!r}: shapes or dtypes differ")
        if self.nbytes:
            self.device.keep_until_done([a.host for a in (self, other) if a.host is not None])
            cl.enqueue_copy(self.device.queue, self.buffer, other.buffer, byte_count=self.nbytes)
            self._mirror = None
        return self

    def copy_from_buffer(self, buffer) -> "DeviceArray":
        """Fill the array from the start of OpenCL ``buffer`` (at least ``nbytes`` long: a
        scratch buffer's result kept), on the device."""
        import pyopencl as cl

        if self.nbytes:
            self.device.keep_until_done([self.host] if self.host is not None else [])
            cl.enqueue_copy(self.device.queue, self.buffer, buffer, byte_count=self.nbytes)
            self._mirror = None
        return self

    def add_(self, other: "DeviceArray | torch.Tensor", alpha: float = 1.0) -> "DeviceArray":
        """``self += alpha * other`` on the device (float arrays); a tensor ``other`` (same
        element count) is uploaded first."""
        if isinstance(other, torch.Tensor):
            other = DeviceArray.of(self.device, other.to(self.dtype), "addend")
        if other.dtype != self.dtype or other.numel() != self.numel():
            raise InputError(f"add_: {other!r} into {self!r}: sizes or dtypes differ")
        n = self.numel()
        if n:
            kernel = self.device.kernel("common/axpy.cl", "axpy", real_of(self.dtype, "add_"))
            self.device.launch(kernel, n, dict(n=np.int64(n), a=numpy_real(self.dtype)(alpha), x=other, y=self))
            self._mirror = None
        return self

    # -- host <-> device ------------------------------------------------------------------

    def _check_like(self, t: torch.Tensor, what: str) -> None:
        if t.dtype != self.dtype or t.numel() != self.numel():
            raise InputError(
                f"{what}: a {t.dtype} tensor of shape {list(t.shape)} does not fit a "
                f"{self.dtype} array of shape {list(self.shape)}"
            )

    def write(self, t: torch.Tensor, what: str = "tensor") -> "DeviceArray":
        """Copy tensor ``t`` (same dtype and element count, any torch device) into the array."""
        import pyopencl as cl

        t = host_tensor(t, self.device, what)
        self._check_like(t, what)
        if not self.nbytes:
            return self
        if self.aliased:
            if t.data_ptr() != self.host.data_ptr():
                self.device.finish()  # no kernel may still read the memory being overwritten
                self.host.view(-1).copy_(t.view(-1))
        else:
            cl.enqueue_copy(self.device.queue, self.buffer, t.detach().numpy(), is_blocking=True)
            self.device.queue_drained()
            self.device.transfers.count(to_device=self.nbytes)
            self._mirror = None
        return self

    def read(self, out: torch.Tensor | None = None) -> torch.Tensor:
        """The array's values as a new CPU tensor, or copied into ``out`` (contiguous, CPU)."""
        import pyopencl as cl

        if out is None:
            out = torch.empty(self.shape, dtype=self.dtype)
        elif out.device.type != "cpu" or not out.is_contiguous():
            raise InputError("read: out must be a contiguous CPU tensor")
        self._check_like(out, "read")
        if not self.nbytes:
            return out
        if self.aliased:
            out.view(-1).copy_(self._synced_host().view(-1))
        else:
            cl.enqueue_copy(self.device.queue, out.numpy(), self.buffer, is_blocking=True)
            self.device.queue_drained()
            self.device.transfers.count(to_host=self.nbytes)
        return out

    def _synced_host(self) -> torch.Tensor:
        """The aliased host tensor, current: a blocking map waits for the kernels writing it
        and, by OpenCL's rules for host-pointer buffers, makes the host memory current."""
        import pyopencl as cl

        mapped, _ = cl.enqueue_map_buffer(
            self.device.queue, self.buffer, cl.map_flags.READ, 0, (self.nbytes,), np.uint8, is_blocking=True
        )
        mapped.base.release(self.device.queue)
        self.device.queue_drained()
        return self.host

    def host_view(self) -> torch.Tensor:
        """The array as a CPU tensor to inspect or edit in place: the array's own memory on a
        zero-copy device; otherwise a mirror read once, whose edits :meth:`push_host_edits`
        sends to the device and which is read again after the device wrote the array
        (:meth:`device_wrote`)."""
        if self.aliased:
            return self._synced_host()
        if self._mirror is None:
            self._mirror = self.read()
            self._mirror_version = self._mirror._version
        return self._mirror

    def push_host_edits(self) -> None:
        """Send in-place edits of the host view's mirror to the device (copy mode; a no-op
        when nothing was edited or the array is the host's memory)."""
        mirror = self._mirror
        if mirror is not None and mirror._version != self._mirror_version:
            self.write(mirror)
            self._mirror, self._mirror_version = mirror, mirror._version

    def device_wrote(self) -> None:
        """Kernels wrote the array: a mirror handed out before is out of date."""
        self._mirror = None


# -- dataclasses of arrays ---------------------------------------------------------------


def _map_arrays(obj: Any, fn) -> Any:
    """A copy of dataclass ``obj`` with ``fn`` applied to each tensor / DeviceArray field."""
    changes = {}
    for f in fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, (torch.Tensor, DeviceArray)):
            changes[f.name] = fn(value, f.name)
    return replace(obj, **changes)


def to_device(obj: Any, device: "Device", alias: bool = False) -> Any:
    """Dataclass ``obj`` with every tensor field uploaded into a new :class:`DeviceArray`
    (other fields kept), e.g. a host :class:`~clflow.mpm.substep.State` -> its device twin;
    ``alias``: the tensors' own memory where the device shares it (:meth:`DeviceArray.alias`)."""
    assert is_dataclass(obj)
    make = DeviceArray.alias if alias else DeviceArray.of
    return _map_arrays(obj, lambda v, name: v if isinstance(v, DeviceArray) else make(device, v.detach(), name))


def to_host(obj: Any) -> Any:
    """Dataclass ``obj`` with every DeviceArray field read into a new CPU tensor."""
    assert is_dataclass(obj)
    return _map_arrays(obj, lambda v, name: v.read() if isinstance(v, DeviceArray) else v)


def arrays_of(obj: Any) -> list[DeviceArray]:
    """The DeviceArray fields of dataclass ``obj``, in field order."""
    return [v for v in (getattr(obj, f.name) for f in fields(obj)) if isinstance(v, DeviceArray)]
