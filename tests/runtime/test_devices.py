"""Device discovery and selection, the program builder and the kernel cache."""

import dataclasses
import os
import subprocess
import sys

import pytest

from clflow.errors import DeviceError, KernelBuildError
from clflow.runtime import devices as devmod
from clflow.runtime import discovery, programs

POCL_CPU = discovery.DeviceInfo(
    platform="Portable Computing Language",
    name="pthread-skylake",
    type="CPU",
    opencl_version="OpenCL 3.0 PoCL",
    opencl_c_version="OpenCL C 1.2 PoCL",
    driver_version="3.1",
    fp64=True,
    float_atomics=False,
    host_unified_memory=True,
    compute_units=2,
    max_work_group_size=4096,
    local_mem_size=2 << 20,
    global_mem_size=4 << 30,
    max_mem_alloc_size=1 << 30,
)
INTEL_CPU = dataclasses.replace(POCL_CPU, platform="Intel(R) OpenCL", name="Intel(R) Xeon(R) CPU")
NVIDIA_GPU = dataclasses.replace(
    POCL_CPU, platform="NVIDIA CUDA", name="NVIDIA GeForce RTX 4090", type="GPU", host_unified_memory=False
)


def pairs(*infos):
    return [(info, object()) for info in infos]


def test_default_prefers_gpu_then_pocl_cpu_then_any_cpu():
    assert discovery.choose(pairs(INTEL_CPU, POCL_CPU, NVIDIA_GPU), None)[0] == NVIDIA_GPU
    assert discovery.choose(pairs(INTEL_CPU, POCL_CPU), None)[0] == POCL_CPU
    assert discovery.choose(pairs(INTEL_CPU), None)[0] == INTEL_CPU


def test_select_by_name_substring_case_insensitive():
    found = pairs(INTEL_CPU, POCL_CPU, NVIDIA_GPU)
    assert discovery.choose(found, "rtx 4090")[0] == NVIDIA_GPU
    assert discovery.choose(found, "PTHREAD")[0] == POCL_CPU


def test_select_by_platform_and_device():
    found = pairs(INTEL_CPU, POCL_CPU, NVIDIA_GPU)
    assert discovery.choose(found, "portable:pthread")[0] == POCL_CPU
    assert discovery.choose(found, "intel:xeon")[0] == INTEL_CPU


def test_unknown_device_lists_the_available_ones():
    with pytest.raises(DeviceError) as err:
        discovery.choose(pairs(INTEL_CPU, POCL_CPU), "radeon")
    assert "radeon" in str(err.value)
    assert INTEL_CPU.label in str(err.value) and POCL_CPU.label in str(err.value)


def test_ambiguous_name_is_an_error_not_a_silent_pick():
    other = dataclasses.replace(POCL_CPU, name="pthread-other")
    with pytest.raises(DeviceError, match="several devices"):
        discovery.choose(pairs(POCL_CPU, other), "pthread")


def test_this_machine_has_the_pocl_cpu_device(device):
    """What CI's set-up installs; elsewhere (a GPU selected) it says nothing about clflow."""
    if not device.info.is_pocl:
        pytest.skip(f"the selected device is {device.info.label}, not PoCL: CI's set-up is not under test here")
    assert any(info.is_pocl and info.type == "CPU" for info in discovery.list_devices())
    assert device.info.fp64 and device.info.compute_units >= 1


def test_get_device_is_shared_and_follows_the_env(monkeypatch, device):
    monkeypatch.setattr(devmod, "_DEVICES", {})
    monkeypatch.setenv(devmod.ENV_DEVICE, device.info.name[:8])
    first = devmod.get_device()
    assert first.info == device.info
    assert devmod.get_device() is first
    monkeypatch.setenv(devmod.ENV_DEVICE, "no-such-device")
    with pytest.raises(DeviceError, match="available devices"):
        devmod.get_device("no-such-device")


def test_double_on_a_device_without_fp64_is_refused():
    dev = devmod.Device(dataclasses.replace(POCL_CPU, fp64=False), cl_device=None)
    with pytest.raises(DeviceError, match="cl_khr_fp64"):
        dev.kernel("common/reduce.cl", "sum_rows_partial", real="double")


def test_kernels_are_built_once_and_reused(device):
    defines = {"REDUCE_WG": 64, "ROWS_PER_ITEM": 16}
    a = device.kernel("common/reduce.cl", "sum_rows_partial", "float", defines)
    b = device.kernel("common/reduce.cl", "sum_rows_partial", "float", dict(defines))
    assert a is b
    assert device.kernel("common/reduce.cl", "sum_rows_partial", "double", defines) is not a


def test_includes_are_inlined_once(tmp_path, monkeypatch):
    (tmp_path / "common").mkdir()
    (tmp_path / "common" / "a.h").write_text('#include "common/b.h"\nint a_marker;\n')
    (tmp_path / "common" / "b.h").write_text("int b_marker;\n")
    (tmp_path / "k.cl").write_text('#include "common/a.h" /* a and b */\n#include "common/b.h"\nint k_marker;\n')
    monkeypatch.setattr(programs, "kernels_dir", lambda: tmp_path)
    text = programs.load_source("k.cl")
    assert text.count("b_marker") == 1 and "a_marker" in text and "k_marker" in text
    assert text.index("b_marker") < text.index("a_marker") < text.index("k_marker")


def test_circular_and_missing_includes_are_clear_errors(tmp_path, monkeypatch):
    (tmp_path / "x.h").write_text('#include "y.h"\n')
    (tmp_path / "y.h").write_text('#include "x.h"\n')
    (tmp_path / "z.cl").write_text('#include "nope.h"\n')
    monkeypatch.setattr(programs, "kernels_dir", lambda: tmp_path)
    with pytest.raises(KernelBuildError, match="circular #include: x.h -> y.h -> x.h"):
        programs.load_source("x.h")
    with pytest.raises(KernelBuildError, match="not found"):
        programs.load_source("z.cl")
    (tmp_path / "w.cl").write_text("int w;\n#include <nope.h>\n")
    with pytest.raises(KernelBuildError, match=r"^w.cl:2: write includes as #include \"path.h\""):
        programs.load_source("w.cl")


def test_compile_errors_carry_the_build_log(device, monkeypatch):
    monkeypatch.setattr(programs, "load_source", lambda rel: "__kernel void broken(void) { undeclared_x = 1; }")
    with pytest.raises(KernelBuildError, match="undeclared_x"):
        device.program("broken_for_test.cl", "float")


def test_build_options_carry_the_switches():
    opts = programs.build_options(POCL_CPU, "double", {"GRID": 8, "FLAG": True})
    assert "-DREAL=double" in opts and "-DREAL_IS_DOUBLE=1" in opts
    assert "-DCLFLOW_FLOAT_ATOMICS=0" in opts and "-DCLFLOW_OCLGRIND=0" in opts
    assert "-DGRID=8" in opts and "-DFLAG=1" in opts
    with pytest.raises(ValueError, match="invalid macro"):
        programs.build_options(POCL_CPU, "float", {"BAD NAME": 1})


def run_clflow(*args, env=None):
    full_env = {k: v for k, v in os.environ.items() if k not in ("POCL_CACHE_DIR", devmod.ENV_DEVICE)}
    full_env.update(env or {})
    return subprocess.run(
        [sys.executable, "-m", "clflow_cli", *args], capture_output=True, text=True, env=full_env, timeout=120
    )


def test_no_opencl_platform_gives_one_clear_message(tmp_path):
    # an empty vendor dir, and no installed GPU driver taken up (a GPU machine has one)
    res = run_clflow("devices", env={"OCL_ICD_VENDORS": str(tmp_path), "CLFLOW_ADOPT_DRIVERS": "0"})
    assert res.returncode == 1
    assert "pocl-opencl-icd" in res.stderr and "Traceback" not in res.stderr


def test_kernel_cache_goes_to_a_per_user_dir_unless_set(tmp_path):
    res = run_clflow("devices", "--json", env={"XDG_CACHE_HOME": str(tmp_path / "xdg")})
    assert res.returncode == 0, res.stderr
    assert f'"kernel_cache_dir": "{tmp_path / "xdg" / "clflow" / "pocl"}"' in res.stdout
    assert (tmp_path / "xdg" / "clflow" / "pocl").is_dir()
    res = run_clflow("devices", "--json", env={"POCL_CACHE_DIR": str(tmp_path / "mine")})
    assert f'"kernel_cache_dir": "{tmp_path / "mine"}"' in res.stdout
