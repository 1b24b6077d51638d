"""The per-device runtime: a :class:`Device` owns one context and one in-order queue
(created lazily, reused) and caches every program and kernel it builds; :func:`get_device`
gives the shared one of a spec (found and chosen by clflow.runtime.discovery).

The bridge between torch and device memory (``Device.zero_copy``) aliases host memory on
devices that share it; the copy mode (``CLFLOW_BRIDGE=copy``, ``clflow --bridge copy`` or
:func:`set_bridge_mode`) makes every device keep separate buffers and copy explicitly, as a
discrete GPU must, so the tests of that path run on a CPU device too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from clflow.errors import DeviceError
from clflow.runtime.binding import BoundLaunch, Fill, Recording
from clflow.runtime.discovery import DeviceInfo, choose, default_kernel_cache_dir, discover, import_pyopencl
from clflow.runtime.program_cache import ProgramBuilds

if TYPE_CHECKING:
    from clflow.runtime.profile import KernelProfile
    from clflow.runtime.signatures import KernelSignature

log = logging.getLogger("clflow.runtime")
ENV_DEVICE = "CLFLOW_DEVICE"
ENV_BRIDGE = "CLFLOW_BRIDGE"
BRIDGE_MODES = ("auto", "copy")  # auto: alias host memory where the device shares it


SPARE_SCRATCH_BYTES = 256 * 2**20  # scratch memory a device keeps for reuse (take_scratch)
MAX_IN_FLIGHT = 256  # zero-copy arrays kept alive for pending commands before the device is waited for


def round_up(n: int, multiple: int) -> int:
    """Smallest multiple of ``multiple`` that is >= n (and >= multiple)."""
    return max(multiple, -(-n // multiple) * multiple)


_BRIDGE_MODE: str | None = None


def set_bridge_mode(mode: str | None) -> None:
    """``"copy"``: separate device buffers and explicit copies on every device (what a
    discrete GPU does); ``"auto"`` or None: ${ENV_BRIDGE}, else alias host memory where the
    device shares it. Applies to buffers created from now on."""
    global _BRIDGE_MODE
    if mode is not None and mode not in BRIDGE_MODES:
        raise DeviceError(f"bridge mode must be one of {', '.join(BRIDGE_MODES)}, got {mode!r}")
    _BRIDGE_MODE = mode


def bridge_mode() -> str:
    """The bridge mode in force: set_bridge_mode's, else $CLFLOW_BRIDGE, else "auto"."""
    mode = _BRIDGE_MODE or os.environ.get(ENV_BRIDGE, "").strip().lower() or "auto"
    if mode not in BRIDGE_MODES:
        raise DeviceError(f"${ENV_BRIDGE} must be one of {', '.join(BRIDGE_MODES)}, got {mode!r}")
    return mode


@dataclass
class Transfers:
    """Bytes copied between host memory and a device's memory: ``to_device`` and ``to_host``."""

    to_device: int = 0
    to_host: int = 0

    def __post_init__(self) -> None:
        self._lock = threading.Lock()

    def count(self, to_device: int = 0, to_host: int = 0) -> None:
        with self._lock:
            self.to_device += int(to_device)
            self.to_host += int(to_host)

    def mark(self) -> "Transfers":
        """The counts now, to subtract later with :meth:`since`."""
        with self._lock:
            return Transfers(self.to_device, self.to_host)

    def since(self, mark: "Transfers") -> "Transfers":
        """Bytes copied each way since ``mark``."""
        with self._lock:
            return Transfers(self.to_device - mark.to_device, self.to_host - mark.to_host)

    @property
    def total(self) -> int:
        return self.to_device + self.to_host


class Device:
    """One OpenCL device with its context, in-order queue and kernel cache.

    Get instances from :func:`get_device`; they are shared and thread-safe to build on.
    """

    def __init__(self, info: DeviceInfo, cl_device: Any):
        self.info = info
        self.cl_device = cl_device
        self._lock = threading.RLock()
        self._context = None
        self._queue = None
        self._programs: dict[tuple, Any] = {}
        self._arguments: dict[tuple, dict] = {}  # program key -> its kernels' arguments (build_program's)
        self.builds = ProgramBuilds()  # programs compiled and loaded from the program cache
        self._kernels: dict[tuple, Any] = {}
        self._signatures: dict[int, KernelSignature] = {}  # id(cached kernel) -> its arguments
        self._spare_scratch: list[Any] = []  # scratch buffers free for reuse (take_scratch)
        self.transfers = Transfers()  # bytes the bridge copied between host and device
        # host tensors of zero-copy arrays that enqueued commands use: kept alive until the
        # queue has run them (OpenCL keeps its buffers alive, not the memory they alias)
        self._in_flight: dict[int, Any] = {}
        self._sizes: dict[tuple, tuple] = {}  # (global, local) size asked -> what launch enqueues
        self.profile: KernelProfile | None = None  # launches recorded while a profile runs
        self._recording = threading.local()  # .into: the Recording of this thread's Device.recording

    @property
    def zero_copy(self) -> bool:
        """Whether buffers alias torch tensors' host memory (a device sharing the host's
        memory, outside the bridge's copy mode) instead of copying."""
        return self.info.host_unified_memory and bridge_mode() != "copy"

    @property
    def recorder(self) -> Recording | None:
        """The recording this thread's launches go into (inside :meth:`recording`), else None."""
        return getattr(self._recording, "into", None)

    def __repr__(self) -> str:
        return f"Device({self.info.label!r})"

    @property
    def context(self):
        with self._lock:
            if self._context is None:
                cl = import_pyopencl()
                self._context = cl.Context([self.cl_device])
            return self._context

    @property
    def queue(self):
        """The device's one in-order command queue."""
        with self._lock:
            if self._queue is None:
                cl = import_pyopencl()
                self._queue = cl.CommandQueue(self.context)
            return self._queue

    def start_profile(self) -> KernelProfile:
        """Record every launch from now on (clflow.runtime.profile): the queue is replaced by one
        with profiling enabled, after the commands already enqueued have run."""
        from clflow.runtime.profile import KernelProfile

        cl = import_pyopencl()
        with self._lock:
            if self._queue is not None:
                self.finish()
            self._queue = cl.CommandQueue(self.context, properties=cl.command_queue_properties.PROFILING_ENABLE)
            self.profile = KernelProfile()
            return self.profile

    def stop_profile(self) -> dict:
        """Stop recording; the profile's summary (KernelProfile.summary) once the device is done."""
        profile, self.profile = self.profile, None
        if profile is None:
            raise RuntimeError("stop_profile: no profile was started")
        self.finish()
        return profile.summary()

    @property
    def kernel_cache_dir(self) -> Path:
        return Path(os.environ.get("POCL_CACHE_DIR", default_kernel_cache_dir()))

    def require_real(self, real: str) -> None:
        """Raise :class:`DeviceError` unless the device can run ``real`` ("float"/"double")."""
        if real not in ("float", "double"):
            raise ValueError(f"real must be 'float' or 'double', not {real!r}")
        if real == "double" and not self.info.fp64:
            raise DeviceError(f"double precision was requested but device {self.info.name!r} has no cl_khr_fp64")

    # -- programs and kernels -------------------------------------------------------------

    def program(self, source: str, real: str = "float", defines: dict[str, Any] | None = None):
        """Build (once) the program of ``kernels_cl/<source>`` with the given switches: loaded
        from the program cache (clflow.runtime.program_cache) where it holds it, else
        compiled and kept there.

        Args:
            source: path of the ``.cl`` file relative to ``kernels_cl/``.
            real: ``"float"`` or ``"double"``: the ``REAL``/``real`` type of the kernels.
            defines: extra ``-D`` macros (name -> value).
        """
        from clflow.runtime.programs import build_options, build_program, load_source

        self.require_real(real)
        key = (source, real, tuple(sorted((defines or {}).items())))
        with self._lock:
            prog = self._programs.get(key)
            if prog is None:
                text, options = load_source(source), build_options(self.info, real, defines)
                prog, self._arguments[key] = build_program(self, source, text, options)
                self._programs[key] = prog
            return prog

    def count_build(self, compiled: bool, seconds: float) -> None:
        """Count a program ``compiled`` from source (else loaded from the program cache) in
        ``builds`` and a running profile."""
        self.builds.add(compiled, seconds)
        if self.profile is not None:
            self.profile.builds.add(compiled, seconds)

    def kernel(self, source: str, name: str, real: str = "float", defines: dict[str, Any] | None = None):
        """The cached ``cl.Kernel`` ``name`` of ``kernels_cl/<source>`` (built once, reused)."""
        program_key = (source, real, tuple(sorted((defines or {}).items())))
        key = (source, name, *program_key[1:])
        with self._lock:
            kern = self._kernels.get(key)
            if kern is None:
                kern = getattr(self.program(source, real, defines), name)
                self._kernels[key] = kern
                from clflow.runtime.signatures import KernelSignature  # numpy: not at import (CLI --help)

                signature = KernelSignature.of(name, real, self._arguments[program_key][name])
                self._signatures[id(kern)] = signature  # cached kernels live on
                kern.set_scalar_arg_dtypes(signature.scalar_dtypes())
            return kern

    def signature(self, kernel) -> KernelSignature:
        """The argument table of a kernel from :meth:`kernel`."""
        from clflow.runtime.signatures import KernelCallError

        try:
            return self._signatures[id(kernel)]
        except KeyError:
            raise KernelCallError(f"kernel {kernel.function_name}: not one of Device.kernel's") from None

    def launch(
        self,
        kernel,
        global_size: int | Sequence[int],
        args: Mapping[str, Any],
        local_size: int | Sequence[int] | None = 64,
    ):
        """Enqueue ``kernel`` on ``args``, by name (put in the kernel's order and checked
        against its signature: clflow.runtime.signatures), with the global size padded to
        whole work-groups; a :class:`~clflow.runtime.arrays.DeviceArray` is passed as its buffer.

        PoCL has no non-uniform work-groups, so every dimension of ``global_size`` is rounded
        up to a multiple of ``local_size``; kernels guard their tail work-items. ``local_size``
        None leaves the choice to the driver (no padding).
        """
        bound = self.bind(kernel, global_size, args, local_size)
        if self.recorder is not None:  # Device.recording: kept to replay, not enqueued
            bound = self._owned(bound)
            self.recorder.steps.append(bound)
            self.recorder.hosts.update((id(h), h) for h in bound.hosts)
            return None
        if bound.hosts:
            self.keep_until_done(bound.hosts)
        return self.enqueue(bound)

    def bind(
        self, kernel, global_size: int | Sequence[int], args: Mapping[str, Any], local_size: int | Sequence[int] | None
    ) -> BoundLaunch:
        """The launch of :meth:`launch` laid out (arguments checked and in order, arrays as
        their buffers, work sizes padded), to enqueue now or many times
        (clflow.runtime.binding)."""
        gsize, lsize = self.work_sizes(global_size, local_size)
        if not isinstance(args, Mapping):
            from clflow.runtime.signatures import KernelCallError

            raise KernelCallError(f"kernel {kernel.function_name}: pass its arguments by name (a mapping)")
        signature = self.signature(kernel)
        raw, hosts = [], []
        for value in signature.ordered(args):
            buffer = getattr(value, "buffer", None)  # a clflow.runtime.arrays.DeviceArray
            if buffer is None:
                raw.append(value)
            else:
                raw.append(buffer)
                if value.host is not None:
                    hosts.append(value.host)
        return BoundLaunch(kernel, gsize, lsize, raw, signature.time_index, hosts)

    def _owned(self, bound: BoundLaunch) -> BoundLaunch:
        """``bound`` on a kernel object of its own (from the same program) with its arguments
        set now: the cached kernel is shared by every launch site, its own only by this
        launch, so a replay sets just the time."""
        cl = import_pyopencl()
        kernel = cl.Kernel(bound.kernel.program, bound.kernel.function_name)
        kernel.set_scalar_arg_dtypes(self.signature(bound.kernel).scalar_dtypes())
        kernel.set_args(*bound.raw)
        return dataclasses.replace(bound, kernel=kernel, owned=True)

    def enqueue(self, bound: BoundLaunch):
        """Set ``bound``'s arguments (unless its kernel holds them) and enqueue it (its
        zero-copy hosts already kept)."""
        if not bound.owned:
            bound.kernel.set_args(*bound.raw)
        event = import_pyopencl().enqueue_nd_range_kernel(self.queue, bound.kernel, bound.global_size, bound.local_size)
        if self.profile is not None:
            self.profile.record(bound.kernel.function_name, event)
        return event

    @contextlib.contextmanager
    def recording(self) -> Iterator[Recording]:
        """Record the launches and zeroings of the block (bound, not enqueued) into a
        :class:`~clflow.runtime.binding.Recording` for :meth:`replay`; scratch taken meanwhile
        belongs to the recording."""
        if self.recorder is not None:
            raise RuntimeError("Device.recording: already recording")
        self._recording.into = recording = Recording()
        try:
            yield recording
        finally:
            self._recording.into = None

    def replay(self, recording: Recording, t) -> None:
        """Enqueue ``recording``'s steps in order, the time ``t`` (a numpy scalar of the
        kernels' real) set in each launch that takes it, the only argument a replay sets."""
        if recording.hosts:
            self.keep_until_done(list(recording.hosts.values()))
        for step in recording.steps:
            if isinstance(step, Fill):
                step.array.zero_()
                continue
            if step.time_index is not None:
                step.kernel.set_arg(step.time_index, t)
            self.enqueue(step)

    def work_sizes(
        self, global_size: int | Sequence[int], local_size: int | Sequence[int] | None = 64
    ) -> tuple[tuple, tuple | None]:
        """(global, local) work sizes, in work-items per dimension, that :meth:`launch` enqueues
        for these arguments: the local size capped at the device's work-group limit and the
        global padded to whole work-groups (local None: the driver's choice, no padding). Cached:
        a substep asks for the same few again and again."""
        plain = isinstance(global_size, int) and (local_size is None or isinstance(local_size, int))
        key = (global_size, local_size) if plain else None
        sizes = None if key is None else self._sizes.get(key)
        if sizes is not None:
            return sizes
        gsize = (global_size,) if isinstance(global_size, int) else tuple(global_size)
        if local_size is None:
            lsize = None
        else:
            lsize = (local_size,) + (1,) * (len(gsize) - 1) if isinstance(local_size, int) else tuple(local_size)
            lsize = tuple(min(size, self.info.max_work_group_size) for size in lsize)
            gsize = tuple(round_up(g, size) for g, size in zip(gsize, lsize))
        if key is not None and len(self._sizes) < 4096:
            self._sizes[key] = (gsize, lsize)
        return gsize, lsize

    def keep_until_done(self, hosts) -> None:
        """Keep the host memory of zero-copy DeviceArrays (``hosts``: their ``host`` tensors)
        that enqueued commands use alive until the queue has run them (the next
        :meth:`finish` or blocking transfer)."""
        with self._lock:
            self._in_flight.update((id(h), h) for h in hosts)
            crowded = len(self._in_flight) > MAX_IN_FLIGHT
        if crowded:
            self.finish()

    def queue_drained(self) -> None:
        """Called after a blocking command: every earlier command of the in-order queue has run."""
        with self._lock:
            self._in_flight.clear()

    def finish(self) -> None:
        """Wait for every command enqueued on the device."""
        self.queue.finish()
        self.queue_drained()

    def take_scratch(self, nbytes: int):
        """A device-only READ_WRITE buffer of at least ``nbytes``, reused when one is spare.

        Fresh large buffers cost page faults on their first use (a 20 MiB buffer: several
        milliseconds on a CPU device); kernels that need the same scratch call after call
        (the rasteriser's per-entry records) get the same memory back. Return it with
        :meth:`give_back_scratch` once the queue has finished with it.
        """
        with self._lock:
            fits = [buf for buf in self._spare_scratch if nbytes <= buf.size <= 2 * nbytes]
            if fits:
                buf = min(fits, key=lambda b: b.size)
                self._spare_scratch.remove(buf)
            else:
                cl = import_pyopencl()
                buf = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, nbytes)
            if self.recorder is not None:  # a replay writes it: the recording's for good
                self.recorder.scratch.append(buf)
            return buf

    def give_back_scratch(self, buf) -> None:
        """Keep ``buf`` (from :meth:`take_scratch`, no longer in use) for reuse; at most
        SPARE_SCRATCH_BYTES are kept, the most recently given back first (a buffer larger
        than the bound on its own is dropped without evicting the others)."""
        with self._lock:
            if self.recorder is not None and self.recorder.owns(buf):
                return
            kept, total = [], 0
            for spare in [buf] + self._spare_scratch:
                if total + spare.size <= SPARE_SCRATCH_BYTES:
                    kept.append(spare)
                    total += spare.size
            self._spare_scratch = kept


_DEVICES: dict[str, Device] = {}
_DEFAULT_SPEC: str | None = None
_REGISTRY_LOCK = threading.Lock()


def set_default_device(spec: str | None) -> None:
    """Make ``spec`` the device that :func:`get_device` returns when given no spec."""
    global _DEFAULT_SPEC
    _DEFAULT_SPEC = spec


def get_device(spec: str | None = None) -> Device:
    """The shared :class:`Device` for ``spec`` (default: set_default_device, $CLFLOW_DEVICE,
    then the first GPU, PoCL's CPU device, any CPU)."""
    spec = spec or _DEFAULT_SPEC or os.environ.get(ENV_DEVICE) or None
    with _REGISTRY_LOCK:
        if spec in _DEVICES:
            return _DEVICES[spec]
        info, cl_device = choose(discover(), spec)
        device = next((d for d in _DEVICES.values() if d.info == info), None) or Device(info, cl_device)
        _DEVICES[spec] = device
        return device
