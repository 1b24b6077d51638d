"""OpenCL runtime: device selection, program building and the torch bridge.

    from clflow.runtime import get_device
    dev = get_device()                 # $CLFLOW_DEVICE, else first GPU, else PoCL's CPU
    kern = dev.kernel("common/reduce.cl", "sum_rows_partial", real="double", defines=...)
    with dev.bind() as b:              # torch tensors as buffers (zero-copy on CPU devices)
        dev.launch(kern, global_size, [b.input(x), b.output(y), ...])

This module imports neither torch nor pyopencl until a device is used.
"""

from clflow.runtime.devices import (
    Device,
    DeviceInfo,
    default_kernel_cache_dir,
    get_device,
    list_devices,
    round_up,
    set_default_device,
)

__all__ = [
    "Device",
    "DeviceInfo",
    "default_kernel_cache_dir",
    "get_device",
    "list_devices",
    "round_up",
    "set_default_device",
]
