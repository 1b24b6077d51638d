"""Built OpenCL programs kept on disk across processes, so that a second run builds nothing.

Drivers' own caches differ (PoCL keeps one in ``$POCL_CACHE_DIR``; pyopencl leaves PoCL's and
NVIDIA's to them and keeps its own for others) and none says whether a build compiled.
Here each built program is one file, named by
the SHA-256 of what decides its binary (the program text with its headers inlined, the
build options, the platform, device, OpenCL and driver versions), holding the binary and
each kernel's argument table (a program created from a binary need not answer
``clGetKernelArgInfo``). Files are written whole (a temporary file renamed onto the name),
so a process never reads half of one; one the driver refuses (a driver update under the
same version string, a damaged file) is rebuilt from source and replaced.

``$CLFLOW_PROGRAM_CACHE``: the folder (default ``$XDG_CACHE_HOME/clflow/programs``), or
``off`` to build every program from source.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

PROGRAM_CACHE_ENV = "CLFLOW_PROGRAM_CACHE"
FORMAT = 1  # the file layout below; a change makes every older file a miss

log = logging.getLogger("clflow.runtime")


def program_cache_dir() -> Path | None:
    """The folder of built programs: ``$CLFLOW_PROGRAM_CACHE`` (None when it says ``off``),
    else ``$XDG_CACHE_HOME/clflow/programs``."""
    chosen = os.environ.get(PROGRAM_CACHE_ENV, "").strip()
    if chosen.lower() == "off":
        return None
    if chosen:
        return Path(chosen)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "clflow" / "programs"


@dataclass
class ProgramBuilds:
    """How a device got its programs: ``compiled`` from source, ``loaded`` from the cache, and
    the seconds each took in all."""

    compiled: int = 0
    loaded: int = 0
    compile_s: float = 0.0
    load_s: float = 0.0

    def add(self, compiled: bool, seconds: float) -> None:
        if compiled:
            self.compiled, self.compile_s = self.compiled + 1, self.compile_s + seconds
        else:
            self.loaded, self.load_s = self.loaded + 1, self.load_s + seconds


@dataclass(frozen=True)
class CachedProgram:
    """A program's binary for one device and its kernels' arguments: kernel name -> ((argument
    name, declared type name), ...), as clflow.runtime.signatures reads them."""

    binary: bytes
    arguments: dict[str, tuple[tuple[str, str], ...]]


def program_key(text: str, options: list[str], info) -> str:
    """The name of the file of the program ``text`` built with ``options`` for the device of
    ``info`` (a DeviceInfo): a SHA-256 over everything that decides the binary."""
    parts = [f"format {FORMAT}", info.platform, info.name, info.opencl_version, info.driver_version, *options, text]
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()


def load_program(folder: Path | None, key: str) -> CachedProgram | None:
    """The cached program ``key`` in ``folder``, or None (none there, or unreadable)."""
    if folder is None:
        return None
    try:
        data = (folder / f"{key}.clbin").read_bytes()
        header, _, binary = data.partition(b"\n")
        meta = json.loads(header)
        arguments = {name: tuple(tuple(a) for a in args) for name, args in meta["arguments"].items()}
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if meta.get("format") != FORMAT or len(binary) != meta.get("bytes"):
        return None
    return CachedProgram(binary, arguments)


def store_program(folder: Path | None, key: str, program: CachedProgram, source: str) -> None:
    """Write ``program`` as ``key`` in ``folder`` (its ``source`` file named in the header);
    a folder that cannot be written costs later runs a build, not this one its result."""
    if folder is None:
        return
    meta = {"format": FORMAT, "source": source, "bytes": len(program.binary), "arguments": program.arguments}
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{key[:16]}-", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(json.dumps(meta).encode() + b"\n" + program.binary)
            os.replace(tmp, folder / f"{key}.clbin")
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        log.debug("program cache: not kept (%s)", exc)
