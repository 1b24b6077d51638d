"""OpenCL drivers that are installed but not registered with the ICD loader.

The ICD loader (ocl-icd, also inside the pyopencl wheel) finds drivers through ``.icd``
files in ``/etc/OpenCL/vendors`` (or the folder ``$OCL_ICD_VENDORS`` names). GPU containers
often mount the vendor's OpenCL library without such a file, e.g. NVIDIA's
``/usr/local/nvidia/lib64/libnvidia-opencl.so.1``: the GPU is there and OpenCL does not
see it. Before the loader starts, :func:`adopt_unregistered` looks for the NVIDIA, AMD and
Intel libraries in the usual folders and, for the ones without an entry, points
``$OCL_ICD_VENDORS`` at a folder holding the registered entries plus theirs (this process
only); ``clflow devices`` says which file would register each for every program.
``CLFLOW_ADOPT_DRIVERS=0`` turns the adoption off (report only).
"""

from __future__ import annotations

import glob
import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path

#: vendor -> file names of its OpenCL driver library (ICD), most specific first
KNOWN_DRIVERS: dict[str, tuple[str, ...]] = {
    "nvidia": ("libnvidia-opencl.so.1", "libnvidia-opencl.so"),
    "amd": ("libamdocl64.so", "libamdocl-orca64.so"),
    "intel": ("libigdrcl.so", "libintelocl.so"),
}
#: folders where drivers are mounted or installed (plus $LD_LIBRARY_PATH's)
SEARCH_DIRS = (
    "/usr/local/nvidia/lib64",
    "/usr/local/nvidia/lib",
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/opt/rocm/lib",
    "/opt/rocm/opencl/lib",
    "/usr/lib/x86_64-linux-gnu/intel-opencl",
    "/opt/intel/opencl/lib64",
)
ENV_SEARCH_PATH = "CLFLOW_OPENCL_SEARCH_PATH"  # replaces SEARCH_DIRS (os.pathsep-separated)
ENV_ADOPT = "CLFLOW_ADOPT_DRIVERS"
DEFAULT_VENDORS_DIR = "/etc/OpenCL/vendors"
log = logging.getLogger("clflow.runtime")


@dataclass(frozen=True)
class Driver:
    """An OpenCL driver library found on disk: its vendor ("nvidia", "amd", "intel") and path."""

    vendor: str
    path: Path

    @property
    def icd_name(self) -> str:
        return f"{self.vendor}.icd"

    def how_to_register(self) -> str:
        return f"echo {self.path} | sudo tee {DEFAULT_VENDORS_DIR}/{self.icd_name}"


def vendors_dir() -> Path:
    """The folder of ``.icd`` files the ICD loader reads."""
    chosen = os.environ.get("OCL_ICD_VENDORS", "")
    return Path(chosen) if chosen and os.path.isdir(chosen) else Path(DEFAULT_VENDORS_DIR)


def registered_entries() -> dict[str, str]:
    """``.icd`` file name -> the library it names, in the loader's vendors folder."""
    entries = {}
    for icd in sorted(glob.glob(str(vendors_dir() / "*.icd"))):
        try:
            entries[os.path.basename(icd)] = Path(icd).read_text().strip()
        except OSError:
            continue
    return entries


def _search_dirs() -> list[str]:
    chosen = os.environ.get(ENV_SEARCH_PATH)
    if chosen is not None:
        return [d for d in chosen.split(os.pathsep) if d]
    extra = [d for d in os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if d]
    return extra + list(SEARCH_DIRS)


def unregistered_drivers() -> list[Driver]:
    """Known vendor drivers on disk that no ``.icd`` entry names (one per vendor)."""
    named = {os.path.basename(lib) for lib in registered_entries().values()}
    found = []
    for vendor, names in KNOWN_DRIVERS.items():
        if any(name in named for name in names):
            continue
        for folder in _search_dirs():
            hit = next((Path(folder) / n for n in names if (Path(folder) / n).is_file()), None)
            if hit is not None:
                found.append(Driver(vendor, hit))  # the versionless link survives driver updates
                break
    return found


@dataclass(frozen=True)
class Adoption:
    """What :func:`adopt_unregistered` found and whether this process uses it."""

    drivers: tuple[Driver, ...]
    used: bool


_ADOPTION: Adoption | None = None


def _write_entries(folder: Path, entries: dict[str, str]) -> bool:
    """Write one ``.icd`` file per entry into ``folder``; True when the folder then names
    them all. Processes starting together (pytest-xdist workers, Ray tasks) write the same
    folder: each writes its own temporary file, and an entry another process has already
    written counts as written."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for name, library in entries.items():
            target = folder / name
            if target.is_file() and target.read_text().strip() == library:
                continue
            tmp = folder / f".{name}.{os.getpid()}.tmp"
            tmp.write_text(library + "\n")
            os.replace(tmp, target)
        return all((folder / n).read_text().strip() == lib for n, lib in entries.items())
    except OSError:
        return False


def adopt_unregistered(cache: Path) -> Adoption:
    """Make this process's ICD loader see the unregistered drivers (call before it starts;
    runs once): a folder in ``cache`` (clflow's cache folder) with the registered entries and
    one per driver becomes ``$OCL_ICD_VENDORS``; not with CLFLOW_ADOPT_DRIVERS=0 or a
    read-only cache."""
    global _ADOPTION
    if _ADOPTION is not None:
        return _ADOPTION
    drivers = tuple(unregistered_drivers())
    _ADOPTION = Adoption(drivers, False)
    if not drivers or os.environ.get(ENV_ADOPT, "1").strip() == "0":
        return _ADOPTION
    entries = dict(registered_entries())
    # the resolved file: a driver that finds its parts next to itself (PoCL does) must be
    # loaded from where it really lies, not through a link elsewhere
    entries.update({d.icd_name: str(d.path.resolve()) for d in drivers})
    digest = hashlib.sha256(repr(sorted(entries.items())).encode()).hexdigest()[:12]
    folder = Path(cache) / f"icd-{digest}"
    if not _write_entries(folder, entries):
        log.warning(
            "cannot write %s, so this process does not see %s; register %s for every program: %s",
            folder,
            ", ".join(str(d.path) for d in drivers),
            "it" if len(drivers) == 1 else "them",
            "; ".join(d.how_to_register() for d in drivers),
        )
        return _ADOPTION
    os.environ["OCL_ICD_VENDORS"] = str(folder)
    _ADOPTION = Adoption(drivers, True)
    return _ADOPTION
