"""Check clflow on a GPU in one command: the test suite with the GPU selected, then the
benchmarks at GPU scale and the demo, each with its kernel profile (OpenCL profiling events:
launches and device time per kernel, host time and launches per substep), all figures in one
JSON (device, versions, kernel plan, tests, benchmarks, profiles).

    python scripts/gpu_check.py                      # first GPU, device suites, full-size benches
    python scripts/gpu_check.py --suite all          # the whole test suite
    python scripts/gpu_check.py --device pthread --small --suite none   # a dry run on PoCL
    python scripts/gpu_check.py --bench sysid-quick  # also `clflow eval sysid --quick` (minutes)

Run from the repository root (the tests are read from tests/); scripts/gpu_check.sh installs
carried wheels first (docs/gpu.md). Exit status 0 only when every step passed.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SUITES = {
    "device": ["tests/runtime", "tests/mpm", "tests/splat", "tests/flow"],  # everything the kernels touch
    "all": ["tests"],
    "none": [],
}
#: taichi's MLS-MPM in the same run where the peers extra is installed (the GPU yardstick)
PEER = ["--peer", "taichi"] if importlib.util.find_spec("taichi") else []
#: name -> clflow bench arguments, at GPU scale (the sizes of docs/gpu.md's targets) and for a dry
#: run (--small); each runs with --profile but launch (it times the host without profiling events)
BENCHES = {
    "mpm-262k": (
        ["mpm", "--material", "elastic", "--substeps", "50", *PEER],
        ["mpm", "--material", "elastic", "--particles-per-axis", "16", "--grid", "16"],
    ),
    "mpm-all-materials": (
        ["mpm", "--substeps", "20"],
        ["mpm", "--particles-per-axis", "8", "--grid", "16", "--substeps", "2"],
    ),
    "mpm-2.1M": (
        ["mpm", "--material", "elastic", "--particles-per-axis", "128", "--grid", "128", "--substeps", "20", *PEER],
        ["mpm", "--material", "elastic", "--particles-per-axis", "20", "--grid", "24", "--substeps", "2"],
    ),
    "mpm-adjoint": (
        ["mpm-adjoint"],
        ["mpm-adjoint", "--particles", "2000", "--grid", "16", "--frames", "2", "--substeps", "4"],
    ),
    "raster-100k-512": (["raster"], ["raster", "-n", "2000", "--size", "128", "--repeat", "2"]),
    "raster-1M-1024": (
        ["raster", "-n", "1000000", "--size", "1024"],
        ["raster", "-n", "5000", "--size", "256", "--repeat", "2"],
    ),
    "launch": (["launch"], ["launch", "--substeps", "5", "--calls", "10"]),
    "launch-cpu-plan": (["launch"], ["launch", "--substeps", "5", "--calls", "10"]),
    "optimize": (["optimize"], ["optimize", "--gaussians", "2000", "--image", "64", "--frames", "3", "--grid", "12"]),
    # a capture's shape: 200k Gaussians on the object, 404 particles in a surface cell at rest (docs/gpu.md)
    "optimize-1M": (
        ["optimize", "--gaussians", "1000000", "--iterations", "1"],
        ["optimize", "--gaussians", "20000", "--image", "64", "--frames", "3", "--grid", "12", "--iterations", "1"],
    ),
    # the quick set's scenes at the nine's resolution from their truths, each with its own method (Levenberg-Marquardt)
    **{
        f"optimize-{case}": (
            ["optimize", "--case", case, "--at-truth", "--iterations", "1"],
            ["optimize", "--case", case, "--quick", "--at-truth", "--iterations", "1"],
        )
        for case in ("torus", "playdoh", "droplet")
    },
}
#: name -> clflow's global options for that bench (the CPU plan's shapes on the GPU, to compare)
GLOBAL_OPTIONS = {"launch-cpu-plan": ["--kernels", "cpu"]}
#: name -> whole clflow commands ({work}: a fresh folder), timed, with `clflow --profile`
COMMANDS = {
    "demo": (["demo", "{work}/demo"], ["demo", "--quick", "{work}/demo"]),
    "sysid-quick": (["eval", "sysid", "--quick", "-o", "{work}/sysid"], None),
}
DEFAULT_STEPS = [*BENCHES, "demo"]  # sysid-quick when asked for (--bench)


def run(cmd: list[str], log: Path, timeout: float, env: dict) -> tuple[int, float, str]:
    """(exit status, seconds, the output's last 4000 characters); the whole output goes to ``log``."""
    start = time.perf_counter()
    try:
        res = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
        code, out = res.returncode, res.stdout + res.stderr
    except subprocess.TimeoutExpired as exc:
        code, out = 124, f"{exc.stdout or ''}{exc.stderr or ''}\ntimed out after {timeout:.0f} s"
    log.write_text(out if isinstance(out, str) else out.decode(errors="replace"))
    print(f"  {' '.join(cmd[2:])}: exit {code} in {time.perf_counter() - start:.0f} s", flush=True)
    return code, time.perf_counter() - start, out[-4000:]


def select_device(spec: str | None, env: dict) -> dict:
    """The DeviceInfo (as JSON) clflow selects for ``spec`` (its default: the first GPU);
    SystemExit when that fails, or when no spec is given and the selection is no GPU."""
    device_args = ["--device", spec] if spec else []
    res = subprocess.run(
        [sys.executable, "-m", "clflow_cli", *device_args, "devices", "--json"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    if res.returncode != 0:
        raise SystemExit(f"clflow devices failed: {res.stderr.strip()}")
    listing = json.loads(res.stdout)
    selected = next(d for d in listing["devices"] if d["selected"])
    if not spec and selected["type"] != "GPU":
        names = ", ".join(f"{d['platform']}:{d['name']} ({d['type']})" for d in listing["devices"])
        raise SystemExit(f"no GPU among the OpenCL devices ({names}); name one with --device to check it anyway")
    return {**selected, "unregistered_drivers": listing.get("unregistered_drivers", [])}


def test_summary(output: str) -> dict:
    """Counts from pytest's last line ("3 failed, 120 passed, 2 skipped in 9.1s")."""
    counts = {k: int(v) for v, k in re.findall(r"(\d+) (passed|failed|skipped|errors?|deselected)", output)}
    return counts


def run_command(name: str, args, logs: Path, env: dict) -> dict:
    """One of COMMANDS, timed, with its kernel profile; a fresh work folder each time."""
    full, small = COMMANDS[name]
    words = small if args.small and small else full
    work = Path(tempfile.mkdtemp(prefix=f"clflow-{name}-", dir=logs))
    profile = logs / f"{name}-profile.json"
    words = [w.format(work=work) for w in words]
    cmd = [sys.executable, "-m", "clflow_cli", "--profile", str(profile), *words]
    code, seconds, tail = run(cmd, logs / f"{name}.log", args.timeout, env)
    entry = {
        "exit": code,
        "seconds": round(seconds, 1),
        "command": " ".join(["clflow", *words]),
        "output": tail[-2500:],
    }
    if profile.exists():
        entry["profile"] = json.loads(profile.read_text())["results"]
    return entry


def write_record(record: dict, out: Path, *, finished: bool) -> bool:
    """Write ``record`` to ``out`` atomically after every step, so a lease cut short keeps the
    figures of the steps it finished; returns whether every step so far passed."""
    tests_ok = record["tests"] is None or record["tests"]["exit"] == 0
    passed = tests_ok and all(b["exit"] == 0 for b in record["benchmarks"].values())
    record.update(passed=passed, finished=finished)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(json.dumps(record, indent=2, default=str) + "\n")
    os.replace(tmp, out)
    return passed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", help="device name substring (default: the first GPU)")
    parser.add_argument("--suite", choices=list(SUITES), default="device", help="tests to run (default: device)")
    parser.add_argument("--small", action="store_true", help="small benchmark sizes (a dry run on a CPU)")
    parser.add_argument(
        "--bench", action="append", choices=[*BENCHES, *COMMANDS], help="only these benchmarks and commands"
    )
    parser.add_argument("--out", default="gpu_check.json", help="the JSON written (default gpu_check.json)")
    parser.add_argument("--logs", help="folder for each step's full output (default: a temporary folder)")
    parser.add_argument("--timeout", type=float, default=540, help="seconds each step may take")
    args = parser.parse_args(argv)

    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    device = select_device(args.device, env)
    env["CLFLOW_DEVICE"] = f"{device['platform']}:{device['name']}"
    logs = Path(args.logs or tempfile.mkdtemp(prefix="clflow-gpu-check-"))
    logs.mkdir(parents=True, exist_ok=True)
    print(f"device: {env['CLFLOW_DEVICE']} ({device['type']}); logs in {logs}", flush=True)
    record: dict = {"device": device, "suite": args.suite, "small": args.small, "tests": None, "benchmarks": {}}

    if SUITES[args.suite]:
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *SUITES[args.suite]]
        code, seconds, tail = run(cmd, logs / "tests.log", args.timeout, env)
        record["tests"] = {"exit": code, "seconds": round(seconds, 1), **test_summary(tail), "tail": tail[-1500:]}
        write_record(record, Path(args.out), finished=False)

    for name in args.bench or DEFAULT_STEPS:
        if name in COMMANDS:
            record["benchmarks"][name] = run_command(name, args, logs, env)
            write_record(record, Path(args.out), finished=False)
            continue
        full, small = BENCHES[name]
        out_json = logs / f"bench-{name}.json"
        profiled = [] if full[0] == "launch" else ["--profile"]  # the launch bench times the host without events
        bench_args = [*(small if args.small else full), *profiled, "--json", str(out_json)]
        cmd = [sys.executable, "-m", "clflow_cli", *GLOBAL_OPTIONS.get(name, []), "bench", *bench_args]
        code, seconds, tail = run(cmd, logs / f"bench-{name}.log", args.timeout, env)
        entry = {"exit": code, "seconds": round(seconds, 1), "output": tail[-2500:]}
        if code == 0 and out_json.exists():
            bench = json.loads(out_json.read_text())
            entry.update(parameters=bench["parameters"], results=bench["results"])
            record.setdefault("environment", bench["environment"])
        record["benchmarks"][name] = entry
        write_record(record, Path(args.out), finished=False)

    record["passed"] = write_record(record, Path(args.out), finished=True)
    print(f"{'passed' if record['passed'] else 'FAILED'}; wrote {args.out}", flush=True)
    return 0 if record["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
