"""OpenCL platforms and devices: found (with PoCL's kernel cache pointed at a per-user folder
and installed GPU drivers without an ICD entry adopted, clflow.runtime.drivers) and chosen
by name, never silently by index:

* ``spec`` (from ``--device`` or ``CLFLOW_DEVICE``) is a case-insensitive substring of the
  device name, or ``"platform:device"`` with a substring for each part;
* without a spec: the first GPU, else PoCL's CPU device, else any CPU device.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from clflow.errors import DeviceError

INSTALL_HINT = (
    "install an OpenCL driver; on Debian/Ubuntu the CPU one is: apt-get install pocl-opencl-icd ocl-icd-libopencl1"
)


def default_kernel_cache_dir() -> Path:
    """Per-user directory for PoCL's compiled-kernel cache (``$XDG_CACHE_HOME/clflow/pocl``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "clflow" / "pocl"


def configure_kernel_cache() -> Path:
    """Point PoCL's kernel cache at a per-user directory unless the user chose one.

    Must run before the OpenCL runtime is initialised (PoCL reads it when it starts).
    """
    if "POCL_CACHE_DIR" not in os.environ:
        path = default_kernel_cache_dir()
        try:
            path.mkdir(parents=True, exist_ok=True)
            os.environ["POCL_CACHE_DIR"] = str(path)
        except OSError:  # read-only home: PoCL falls back to its own default
            pass
    return Path(os.environ.get("POCL_CACHE_DIR", default_kernel_cache_dir()))


def import_pyopencl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # libOpenCL.so missing or pyopencl not installed
        raise DeviceError(f"cannot load the OpenCL runtime ({exc}); {INSTALL_HINT}") from None
    return cl


@dataclass(frozen=True)
class DeviceInfo:
    """What clflow needs to know about an OpenCL device (sizes in bytes)."""

    platform: str
    name: str
    type: str  # "GPU", "CPU", "ACCELERATOR" or "OTHER"
    opencl_version: str
    opencl_c_version: str
    driver_version: str
    fp64: bool
    float_atomics: bool  # cl_ext_float_atomics present (kernels also check the feature macros)
    host_unified_memory: bool  # host and device share memory: buffers can alias tensors
    compute_units: int
    max_work_group_size: int
    local_mem_size: int
    global_mem_size: int
    max_mem_alloc_size: int  # the largest single buffer
    int64_atomics: bool = False  # cl_khr_int64_base_atomics (float64 compare-and-swap atomics)

    @property
    def is_pocl(self) -> bool:
        return "portable computing language" in self.platform.lower() or "pocl" in self.platform.lower()

    @property
    def is_oclgrind(self) -> bool:
        return "oclgrind" in self.platform.lower()

    @property
    def label(self) -> str:
        """``platform:device``, the form accepted by ``--device``."""
        return f"{self.platform}:{self.name}"


def _device_type(cl, dev) -> str:
    t = dev.type
    for name in ("GPU", "CPU", "ACCELERATOR"):
        if t & getattr(cl.device_type, name):
            return name
    return "OTHER"


def _describe(cl, platform, dev) -> DeviceInfo:
    extensions = set(dev.extensions.split())
    dtype = _device_type(cl, dev)
    try:
        unified = bool(dev.host_unified_memory)
    except cl.Error:  # removed from the OpenCL 3.0 core query set on some drivers
        unified = False
    return DeviceInfo(
        platform=platform.name.strip(),
        name=dev.name.strip(),
        type=dtype,
        opencl_version=dev.version.strip(),
        opencl_c_version=dev.opencl_c_version.strip(),
        driver_version=dev.driver_version.strip(),
        fp64="cl_khr_fp64" in extensions,
        float_atomics="cl_ext_float_atomics" in extensions,
        host_unified_memory=unified or dtype == "CPU",
        compute_units=int(dev.max_compute_units),
        max_work_group_size=int(dev.max_work_group_size),
        local_mem_size=int(dev.local_mem_size),
        global_mem_size=int(dev.global_mem_size),
        max_mem_alloc_size=int(dev.max_mem_alloc_size),
        int64_atomics="cl_khr_int64_base_atomics" in extensions,
    )


def discover() -> list[tuple[DeviceInfo, Any]]:
    """All (info, pyopencl.Device) pairs of all platforms, in platform order (installed GPU
    drivers without an ICD entry included: clflow.runtime.drivers)."""
    from clflow.runtime.drivers import adopt_unregistered

    cache = configure_kernel_cache()
    adoption = adopt_unregistered(cache.parent)
    cl = import_pyopencl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    found = []
    for platform in platforms:
        try:
            devices = platform.get_devices()
        except cl.Error:  # a platform with no devices raises DEVICE_NOT_FOUND
            continue
        found.extend((_describe(cl, platform, d), d) for d in devices)
    if not found:
        unused = (
            ""
            if adoption.used
            else "".join(
                f"; the {d.vendor} driver {d.path} is installed without an ICD entry: {d.how_to_register()}"
                for d in adoption.drivers
            )
        )
        raise DeviceError(f"no OpenCL platform or device found{unused}; {INSTALL_HINT}")
    return found


def list_devices() -> list[DeviceInfo]:
    """Every OpenCL device of every platform."""
    return [info for info, _ in discover()]


def _matches(info: DeviceInfo, spec: str) -> bool:
    spec = spec.strip().lower()
    if ":" in spec:
        plat, _, dev = spec.partition(":")
        return plat.strip() in info.platform.lower() and dev.strip() in info.name.lower()
    return spec in info.name.lower() or spec == info.platform.lower()


def choose(found: list[tuple[DeviceInfo, Any]], spec: str | None) -> tuple[DeviceInfo, Any]:
    if spec:
        hits = [pair for pair in found if _matches(pair[0], spec)]
        available = "\n".join(f"  {info.label} ({info.type})" for info, _ in found)
        if not hits:
            raise DeviceError(f"no OpenCL device matches {spec!r}; available devices:\n{available}")
        if len(hits) > 1:
            names = "\n".join(f"  {info.label}" for info, _ in hits)
            raise DeviceError(f"{spec!r} matches several devices; use a longer name or 'platform:device':\n{names}")
        return hits[0]
    for want in (
        lambda i: i.type == "GPU",
        lambda i: i.is_pocl and i.type == "CPU",
        lambda i: i.type == "CPU",
        lambda i: True,
    ):
        for pair in found:
            if want(pair[0]):
                return pair
    raise AssertionError("unreachable: discover never returns an empty list")
