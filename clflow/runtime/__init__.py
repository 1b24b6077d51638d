"""OpenCL runtime: device selection, program building and the torch bridge.

    from clflow.runtime import get_device
    dev = get_device()                 # $CLFLOW_DEVICE, else first GPU, else PoCL's CPU
    kern = dev.kernel("common/reduce.cl", "sum_rows_partial", real="double", defines=...)
    with bind(dev) as b:               # one call's torch tensors as buffers (clflow.runtime.bridge)
        dev.launch(kern, global_size, {"x": b.input(x), "partial": b.output(y), ...})  # by name
    y = DeviceArray.of(dev, x)         # state that stays on the device (clflow.runtime.arrays)
    dev.launch(kern, global_size, {"x": y, ...}); y.read()

This module imports neither torch nor pyopencl until a device is used.
"""

from clflow.runtime.devices import Device, bridge_mode, get_device, round_up, set_bridge_mode, set_default_device
from clflow.runtime.discovery import DeviceInfo, default_kernel_cache_dir, list_devices

__all__ = [
    "Device",
    "bridge_mode",
    "set_bridge_mode",
    "DeviceInfo",
    "default_kernel_cache_dir",
    "get_device",
    "list_devices",
    "round_up",
    "set_default_device",
]
