"""Kernel calls by name.

Each kernel's argument table is its own OpenCL C signature, read back from the driver
(every program is built with ``-cl-kernel-arg-info``), so the ``.cl`` file stays the one
place that says what a kernel takes. A host call names every argument
(``device.launch(kernel, n, {"n": np.int32(n), "x": x, ...})``); a name missing or unknown,
a pointer given a scalar (or the reverse), or an array or scalar of the wrong kind or width
is refused before anything is enqueued, naming the kernel and the argument.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

#: OpenCL C scalar type -> numpy type of the same kind and width
SCALAR_TYPES = {
    "char": np.int8,
    "uchar": np.uint8,
    "short": np.int16,
    "ushort": np.uint16,
    "int": np.int32,
    "uint": np.uint32,
    "long": np.int64,
    "ulong": np.uint64,
    "float": np.float32,
    "double": np.float64,
}

# clGetKernelArgInfo parameters (OpenCL 1.2): the argument's declared type name and its name
_ARG_TYPE_NAME, _ARG_NAME = 0x1198, 0x119A


class KernelCallError(TypeError):
    """A kernel called with arguments its signature does not take: a bug in clflow, not in
    the user's input, so it keeps its traceback."""


def kernel_arguments(kernel) -> tuple[tuple[str, str], ...]:
    """((name, declared type name), ...) of a ``cl.Kernel`` built from source with
    ``-cl-kernel-arg-info``, in order."""
    return tuple(
        (kernel.get_arg_info(i, _ARG_NAME), kernel.get_arg_info(i, _ARG_TYPE_NAME).replace(" ", ""))
        for i in range(kernel.num_args)
    )


@dataclass(frozen=True)
class KernelArgument:
    """One argument of a kernel: its name and declared type ("int", "real", "real*", ...)."""

    name: str
    type_name: str  # a pointer's ends in "*"


@dataclass(frozen=True)
class KernelSignature:
    """A kernel's name, what ``real`` means in its program, and its arguments in order."""

    kernel: str
    real: str
    arguments: tuple[KernelArgument, ...]

    @staticmethod
    def of(kernel: str, real: str, arguments) -> "KernelSignature":
        """The signature of kernel ``kernel`` of a program built with ``REAL=real`` whose
        ``arguments`` are ((name, type name), ...) (:func:`kernel_arguments`)."""
        return KernelSignature(kernel, real, tuple(KernelArgument(name, type_name) for name, type_name in arguments))

    def __post_init__(self):
        # the kinds of argument values already checked against this signature: a call site
        # repeats its kinds, so only its first call pays for the checks (their cost:
        # docs/architecture.md, "Runtime")
        object.__setattr__(self, "_checked", set())
        object.__setattr__(self, "_names", tuple(a.name for a in self.arguments))

    @property
    def time_index(self) -> int | None:
        """The position of the argument ``t`` (a substep's time), None where there is none."""
        return self._names.index("t") if "t" in self._names else None

    def scalar_dtypes(self) -> list:
        """Per argument, the numpy dtype of a scalar (``real`` resolved) or None (a pointer,
        struct or image): what ``cl.Kernel.set_scalar_arg_dtypes`` takes. Declared, pyopencl
        packs the scalars itself instead of inspecting each on every call (the cost:
        docs/architecture.md, "Runtime")."""
        return [self._dtype(a.type_name) if a.type_name in (*SCALAR_TYPES, "real") else None for a in self.arguments]

    def _dtype(self, type_name: str) -> np.dtype:
        """The numpy dtype of an OpenCL scalar type name or of a pointer's target (``real`` resolved)."""
        base = type_name.rstrip("*")
        return np.dtype(SCALAR_TYPES[self.real if base == "real" else base])

    def ordered(self, args: Mapping[str, Any]) -> list:
        """``args`` (name -> value) in the kernel's argument order, each checked against its type."""
        names = self._names
        if len(args) == len(names):
            try:
                values = [args[n] for n in names]
            except KeyError:
                values = None
            if values is not None:
                kinds = tuple([(type(v), getattr(v, "dtype", None)) for v in values])
                if kinds in self._checked:
                    return values
        missing, unknown = [n for n in names if n not in args], sorted(set(args) - set(names))
        problems = ([f"missing {', '.join(missing)}"] if missing else []) + (
            [f"unknown {', '.join(unknown)}"] if unknown else []
        )
        if problems:
            raise KernelCallError(f"kernel {self.kernel}: {'; '.join(problems)} (it takes {', '.join(names)})")
        for argument in self.arguments:
            self._check(argument, args[argument.name])
        self._checked.add(kinds)
        return values

    def _kind(self, type_name: str) -> tuple[str, int]:
        """("f" or "i", bytes) of an OpenCL scalar type name (``real`` resolved)."""
        dtype = self._dtype(type_name)
        return ("f" if dtype.kind == "f" else "i"), dtype.itemsize

    def _check(self, argument: KernelArgument, value: Any) -> None:
        where = f"kernel {self.kernel}: argument {argument.name} ({argument.type_name})"
        if argument.type_name.rstrip("*") not in (*SCALAR_TYPES, "real"):
            return  # a struct or an image: not checked here
        if argument.type_name.endswith("*"):
            if isinstance(value, (np.generic, int, float)):
                raise KernelCallError(f"{where} is a pointer, given the number {value}")
            dtype = getattr(value, "dtype", None)  # a DeviceArray's torch dtype; a bare cl.Buffer has none
            if dtype is not None:
                given = ("f" if dtype.is_floating_point else "i", dtype.itemsize)
                if given != self._kind(argument.type_name):
                    raise KernelCallError(f"{where} given an array of {dtype}")
            return
        if not isinstance(value, np.generic):
            raise KernelCallError(f"{where} needs a sized numpy scalar, given {value!r}")
        given = ("f" if value.dtype.kind == "f" else "i", value.dtype.itemsize)
        if given != self._kind(argument.type_name):
            raise KernelCallError(f"{where} given a {value.dtype} scalar")
