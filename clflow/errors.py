"""Exceptions clflow raises for conditions a user can fix.

The CLI turns every :class:`ClflowError` into a one-line message and a non-zero exit;
anything else is a bug and keeps its traceback.
"""


class ClflowError(Exception):
    """Base class of clflow's user-facing errors."""


class DeviceError(ClflowError):
    """No usable OpenCL platform/device, an unknown device name, or a missing capability."""


class KernelBuildError(ClflowError):
    """An OpenCL program failed to compile; the message carries the build log."""


class InputError(ClflowError, ValueError):
    """A tensor, file or parameter that clflow cannot work with."""
