"""The program cache: a second process builds nothing, and a cache that fails costs builds, never a run."""

from __future__ import annotations

import hashlib
import json
import os

import pytest

from clflow.runtime.devices import Device
from clflow.runtime.program_cache import PROGRAM_CACHE_ENV
from tests._helpers import run_python

SOURCE, KERNEL = "common/reduce.cl", "sum_rows_partial"
DEFINES = {"REDUCE_WG": 64, "ROWS_PER_ITEM": 16}

BUILD = f"""
import json
from clflow.runtime import get_device
device = get_device()
kernel = device.kernel({SOURCE!r}, {KERNEL!r}, "double", {DEFINES!r})
print(json.dumps({{"compiled": device.builds.compiled, "loaded": device.builds.loaded,
                  "arguments": [[a.name, a.type_name] for a in device.signature(kernel).arguments]}}))
"""


def build_in_a_process(cache) -> dict:
    env = {**os.environ, PROGRAM_CACHE_ENV: str(cache)}
    return json.loads(run_python(BUILD, env=env).stdout.splitlines()[-1])


def fresh(device: Device) -> Device:
    """A Device of the same OpenCL device that has built nothing yet (its own context)."""
    return Device(device.info, device.cl_device)


def test_a_second_process_builds_nothing_and_gets_the_same_kernel_arguments(tmp_path):
    first = build_in_a_process(tmp_path)
    second = build_in_a_process(tmp_path)
    assert (first["compiled"], first["loaded"]) == (1, 0)
    assert (second["compiled"], second["loaded"]) == (0, 1)
    assert second["arguments"] == first["arguments"] and ["x", "real*"] in first["arguments"]
    assert len(list(tmp_path.glob("*.clbin"))) == 1 and not list(tmp_path.glob(".*.tmp"))


def test_a_refused_or_damaged_program_is_compiled_again_and_replaced(device, tmp_path, monkeypatch):
    monkeypatch.setenv(PROGRAM_CACHE_ENV, str(tmp_path))
    mine = tmp_path / "notes.txt"  # a file of the user's in the folder: never touched
    mine.write_text("mine")
    before = hashlib.sha256(mine.read_bytes()).hexdigest()
    fresh(device).program(SOURCE, "double", DEFINES)
    (cached,) = tmp_path.glob("*.clbin")
    header, _, binary = cached.read_bytes().partition(b"\n")
    for damaged in (header + b"\n" + b"\x00" * len(binary), header[:-5] + b"\n" + binary, b""):
        cached.write_bytes(damaged)  # a binary the driver refuses, a broken header, an empty file
        again = fresh(device)
        kernel = again.kernel(SOURCE, KERNEL, "double", DEFINES)
        assert (again.builds.compiled, again.builds.loaded) == (1, 0)
        assert [a.name for a in again.signature(kernel).arguments][:2] == ["x", "partial"]
        assert cached.read_bytes().partition(b"\n")[2] == binary  # replaced by the rebuilt program
    loaded = fresh(device)
    loaded.program(SOURCE, "double", DEFINES)
    assert (loaded.builds.compiled, loaded.builds.loaded) == (0, 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([cached.name, mine.name])  # no temporary left
    assert hashlib.sha256(mine.read_bytes()).hexdigest() == before


@pytest.mark.parametrize("cache", ["off", "a file"])
def test_without_a_usable_cache_every_build_compiles_and_runs(device, tmp_path, monkeypatch, cache):
    blocker = tmp_path / "a file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(PROGRAM_CACHE_ENV, "off" if cache == "off" else str(blocker))
    for _ in range(2):
        again = fresh(device)
        again.kernel(SOURCE, KERNEL, "double", DEFINES)
        assert (again.builds.compiled, again.builds.loaded) == (1, 0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a file"]


def test_the_profile_counts_the_builds_it_saw(device, tmp_path, monkeypatch):
    from clflow.runtime.profile import format_profile

    monkeypatch.setenv(PROGRAM_CACHE_ENV, str(tmp_path))
    fresh(device).program(SOURCE, "double", DEFINES)
    again = fresh(device)
    again.start_profile()
    again.program(SOURCE, "double", DEFINES)
    again.program(SOURCE, "float", DEFINES)
    report = again.stop_profile()
    assert (report["builds"]["compiled"], report["builds"]["loaded"]) == (1, 1)
    assert "programs: 1 compiled" in format_profile(report) and "1 loaded from the program cache" in format_profile(
        report
    )
