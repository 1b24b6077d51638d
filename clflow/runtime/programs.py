"""Finding OpenCL C sources in ``kernels_cl/``, the switches they are built with, and
building them (through the program cache, clflow.runtime.program_cache).

``#include "path.h"`` lines are resolved here, against ``kernels_cl/`` (the include path),
and inlined, so the text handed to the driver is self-contained: the driver's kernel cache
(PoCL's hashes the program text and options) then also sees every header change, and tools
such as oclgrind need no include flags.
"""

from __future__ import annotations

import functools
import logging
import re
import time
import warnings
from pathlib import Path
from typing import Any

from clflow.errors import KernelBuildError

# AMD chips whose global memory has a float atomic add (__builtin_amdgcn_global_atomic_fadd_*)
AMD_GLOBAL_FADD_CHIPS = ("gfx90a", "gfx940", "gfx941", "gfx942", "gfx950")
SLOW_BUILD_SECONDS = 1.0  # a program build longer than this compiled (PoCL's cache answers in ms)
log = logging.getLogger("clflow.runtime")
# an include line, a trailing comment allowed; any other line that starts #include is refused
_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*(?://.*|/\*.*\*/\s*)?$')
_ANY_INCLUDE = re.compile(r"^\s*#\s*include\b")


@functools.lru_cache(maxsize=1)
def kernels_dir() -> Path:
    """Root of the OpenCL sources: inside the installed package, else the source checkout."""
    package = Path(__file__).resolve().parent.parent  # .../clflow
    for candidate in (package / "kernels_cl", package.parent / "kernels_cl"):
        if (candidate / "common").is_dir():
            return candidate
    raise KernelBuildError(
        f"OpenCL sources not found next to {package} (looked for kernels_cl/ in the package "
        "and in the source checkout); reinstall clflow"
    )


def load_source(relpath: str) -> str:
    """Text of ``kernels_cl/<relpath>`` with its ``#include "..."`` lines inlined (once each)."""
    root = kernels_dir()
    seen: set[Path] = set()

    def expand(path: Path, stack: tuple[Path, ...]) -> list[str]:
        if path in stack:
            chain = " -> ".join(p.relative_to(root).as_posix() for p in stack + (path,))
            raise KernelBuildError(f"circular #include: {chain}")
        if path in seen:
            return []
        if not path.is_file():
            raise KernelBuildError(f"OpenCL source not found: {path}")
        seen.add(path)
        lines = [f'#line 1 "{path.relative_to(root).as_posix()}"']
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            match = _INCLUDE.match(line)
            if match is None and _ANY_INCLUDE.match(line):
                where = f"{path.relative_to(root).as_posix()}:{number}"
                raise KernelBuildError(f'{where}: write includes as #include "path.h" (from kernels_cl/), not {line!r}')
            if match:
                target = (root / match.group(1)).resolve()
                lines.extend(expand(target, stack + (path,)))
                lines.append(f'#line {number + 1} "{path.relative_to(root).as_posix()}"')
            else:
                lines.append(line)
        return lines

    return "\n".join(expand((root / relpath).resolve(), ())) + "\n"


def build_options(info, real: str, defines: dict[str, Any] | None = None) -> list[str]:
    """Compiler options: kernel argument info, the ``REAL`` switch, the feature defines and
    any extra ``-D``.

    Defines every kernel can rely on:
      REAL (float|double), REAL_IS_DOUBLE (0|1), CLFLOW_FLOAT_ATOMICS (0|1: the device
      announces cl_ext_float_atomics), CLFLOW_AMD_GLOBAL_FADD (0|1: an AMD chip with global
      float atomic add), CLFLOW_OCLGRIND (0|1: running under oclgrind).
    """
    opts = [
        "-cl-kernel-arg-info",  # argument names and types: launches by name are checked against them
        f"-DREAL={real}",
        f"-DREAL_IS_DOUBLE={int(real == 'double')}",
        f"-DCLFLOW_FLOAT_ATOMICS={int(info.float_atomics)}",
        f"-DCLFLOW_AMD_GLOBAL_FADD={int(info.name.lower().startswith(AMD_GLOBAL_FADD_CHIPS))}",
        f"-DCLFLOW_OCLGRIND={int(info.is_oclgrind)}",
    ]
    if info.float_atomics and "3." in info.opencl_c_version:
        opts.append("-cl-std=CL3.0")  # cl_ext_float_atomics builds on the OpenCL C 3.0 atomics
    for name, value in sorted((defines or {}).items()):
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise ValueError(f"invalid macro name {name!r}")
        opts.append(f"-D{name}={int(value) if isinstance(value, bool) else value}")
    return opts


def build_program(device, source: str, text: str, options: list[str]):
    """(program, its kernels' arguments: name -> ((argument, type name), ...)) of ``text``
    built with ``options``: the cached binary where the cache holds one the driver takes,
    else compiled from source and cached. Counted in ``builds`` and a running profile."""
    import pyopencl as cl  # a device exists: pyopencl is there

    from clflow.runtime import program_cache as cache

    folder = None if device.info.is_oclgrind else cache.program_cache_dir()  # oclgrind reports on the source
    name = cache.program_key(text, options, device.info)
    cached = cache.load_program(folder, name)
    started = time.perf_counter()
    if cached is not None:
        try:
            prog = cl.Program(device.context, [device.cl_device], [cached.binary]).build(options=options)
        except cl.Error as exc:
            log.info("kernels_cl/%s: the driver refused the cached program (%s); compiling it", source, exc)
        else:
            device.count_build(False, time.perf_counter() - started)
            return prog, cached.arguments
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            prog = cl.Program(device.context, text).build(options=options)
    except cl.RuntimeError as exc:
        raise KernelBuildError(
            f"building kernels_cl/{source} ({' '.join(options)}) failed on {device.info.name}:\n{exc}"
        ) from None
    seconds = time.perf_counter() - started
    device.count_build(True, seconds)
    if seconds > SLOW_BUILD_SECONDS:  # a real compile, not the driver's cache: say why it waits
        log.info("compiled kernels_cl/%s in %.1f s (cached for later runs)", source, seconds)
    from clflow.runtime.signatures import kernel_arguments

    arguments = {k.function_name: kernel_arguments(k) for k in prog.all_kernels()}
    try:
        binary = prog.binaries[0]
    except cl.Error:  # a driver that gives no binaries: every process compiles
        binary = b""
    if binary:
        cache.store_program(folder, name, cache.CachedProgram(binary, arguments), source)
    return prog, arguments
