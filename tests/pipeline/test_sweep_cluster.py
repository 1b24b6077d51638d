"""``clflow sweep`` on a Ray cluster of two nodes on this machine (``ray start --head`` and a
second node joined by its address, docs/sweep.md), the second node's raylet killed while it
runs a task: its run is recorded as killed, none is lost or reported ok, ``--retry-failed``
completes it, and the records and outputs are a serial run's."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

# the nodes and the driver: no token (Ray 2.60 asks for one by default), no usage report
RAY_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}
STARTED = "Ray runtime started"  # what `ray start --block` prints once its node is up


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """Ray nodes started here with `ray start --block`, each in its own session (so each of
    their processes, Ray's workers included, is found by its session id and ended), with
    their own temporary folders and free ports (not those of another Ray on this machine)."""

    def __init__(self):
        self.port = _free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.nodes: list[tuple[subprocess.Popen, Path]] = []
        self.env = {**os.environ, **RAY_ENV}

    def start(self, resources: dict, head: bool = False, timeout: float = 120) -> subprocess.Popen:
        temp = Path(tempfile.mkdtemp(prefix="clflow-ray-", dir="/tmp"))  # short: Ray's socket paths
        ray = os.path.join(os.path.dirname(sys.executable), "ray")
        ports = [
            "--node-manager-port", "--object-manager-port", "--dashboard-agent-listen-port",
            "--dashboard-agent-grpc-port", "--runtime-env-agent-port", "--metrics-export-port",
        ]  # fmt: skip
        where = ["--head", "--port", str(self.port), "--include-dashboard", "false"] if head else []
        where += ["--dashboard-port", str(_free_port())] if head else ["--address", self.address]
        command = [ray, "start", *where, "--node-ip-address", "127.0.0.1", "--temp-dir", str(temp), "--block"]
        command += ["--num-cpus", "1", "--resources", json.dumps(resources), "--object-store-memory", str(80 << 20)]
        command += [arg for port in ports for arg in (port, str(_free_port()))] + ["--disable-usage-stats"]
        log = open(temp / "start.log", "w")
        proc = subprocess.Popen(command, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.nodes.append((proc, temp))
        deadline = time.monotonic() + timeout
        while STARTED not in (temp / "start.log").read_text():
            assert proc.poll() is None and time.monotonic() < deadline, (temp / "start.log").read_text()
            time.sleep(0.2)
        return proc

    def raylet(self, node: subprocess.Popen):
        import psutil

        return next(p for p in psutil.Process(node.pid).children() if p.name() == "raylet")

    def stop(self, more: tuple[int, ...] = ()) -> None:
        """Kill every process of the nodes' sessions (and of the sessions ``more``), then
        remove their folders: nothing is left behind, whatever happened."""
        import psutil

        sessions = {proc.pid for proc, _ in self.nodes} | set(more)
        for _ in range(50):
            left = []
            for p in psutil.process_iter():
                try:
                    if os.getsid(p.pid) in sessions:
                        p.kill()
                        left.append(p)
                except (ProcessLookupError, psutil.Error):
                    pass
            psutil.wait_procs(left, timeout=5)
            if not left:
                break
        for proc, temp in self.nodes:
            proc.wait(timeout=10)
            shutil.rmtree(temp, ignore_errors=True)


@pytest.fixture
def cluster():
    pytest.importorskip("ray")
    pytest.importorskip("psutil")  # (a dependency of ray)
    nodes = Cluster()
    try:
        yield nodes
    finally:
        nodes.stop()


def _kill_when_busy(raylet, killed: dict, stop: threading.Event) -> None:
    """Kill the raylet (SIGKILL) as soon as one of its workers runs a task (Ray titles a
    busy worker ``ray::<function>``, an idle one ``ray::IDLE``)."""
    import psutil

    while not stop.is_set() and raylet.is_running():
        try:
            busy = [w for w in raylet.children() if "_ray_task" in " ".join(w.cmdline())]
        except psutil.Error:  # a worker that just ended
            busy = []
        if busy:
            os.kill(raylet.pid, signal.SIGKILL)
            killed["at"] = time.monotonic()
            return
        time.sleep(0.05)


def _clflow(*args, env, timeout=300):
    """``clflow ARGS`` in its own process (its own session: the test ends it if it hangs)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "clflow_cli", *map(str, args)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        output, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        pytest.fail(f"clflow {' '.join(map(str, args))} hung:\n{output}")
    except BaseException:  # Ctrl-C: not left running
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    return proc.returncode, output


def _results(out: Path) -> dict:
    """Each run's record without its times and host, and its Gaussians."""
    runs = json.loads((out / "sweep.json").read_text())["runs"]
    records = {}
    for name, record in runs.items():
        kept = {k: v for k, v in record.items() if k not in ("seconds", "date", "host", "skipped")}
        if record["status"] == "ok":
            with np.load(out / "runs" / name / "simulation" / "gaussians.npz") as g:
                kept["arrays"] = {k: g[k] for k in g.files}
        records[name] = kept
    return records


def _spec(folder: Path, quick_demo: Path, moduli: list[float]) -> Path:
    """A sweep of the quick demo's simulate, one run for each Young's modulus."""
    (folder / "demo").symlink_to(quick_demo)
    spec = folder / "spec.yaml"
    grid = {"material.parameters.youngs_modulus": moduli}
    command = {"command": "simulate", "base": "demo/config.yaml", "options": {"preview": "none"}}
    spec.write_text(yaml.safe_dump({**command, "set": {"simulation.frames": 48}, "grid": grid}))
    return spec


def _kill_mid_sweep(cluster: Cluster, node: subprocess.Popen, *args) -> tuple[int, str]:
    """``clflow ARGS`` while ``node``'s raylet is killed as soon as it runs a task."""
    killed: dict = {}
    stop = threading.Event()
    watcher = threading.Thread(target=_kill_when_busy, args=(cluster.raylet(node), killed, stop), daemon=True)
    watcher.start()
    try:
        start = time.monotonic()
        code, output = _clflow(*args, env=cluster.env)
    finally:
        stop.set()
        watcher.join(timeout=5)
    assert "at" in killed, f"no task ran on the node:\n{output}"
    print(f"the sweep took {time.monotonic() - start:.1f} s, the node was killed after {killed['at'] - start:.1f} s")
    return code, output


@pytest.mark.slow
def test_a_node_that_dies_mid_sweep_loses_no_run_and_retry_failed_completes_them(cluster, quick_demo, tmp_path):
    spec = _spec(tmp_path, quick_demo, [2.0e3, 4.0e3, 8.0e3, 1.6e4])
    # each node has room for one task (the `slot` each run asks for), so of the first two
    # runs the sweep starts at once, one runs on the second node
    cluster.start({"slot": 1}, head=True)
    second = cluster.start({"slot": 1})
    out = tmp_path / "cluster"
    args = ("sweep", spec, "-o", out, "--address", cluster.address, "--resources", "slot=1")
    code, output = _kill_mid_sweep(cluster, second, *args)
    assert code == 1 and "3 of 4 runs ok" in output, output

    records = json.loads((out / "sweep.json").read_text())["runs"]
    assert len(records) == 4 and records.keys() == {p.name for p in (out / "runs").iterdir()}
    (lost,) = [r for r in records.values() if r["status"] != "ok"]  # recorded, not pending, not ok
    assert lost["status"] == "killed" and "NodeDiedError" in lost["reason"], lost
    assert json.loads((out / "runs" / lost["name"] / "result.json").read_text())["status"] == "killed"
    assert f"not ok: {lost['name']}" in output

    # the head alone finishes it; the three finished runs are skipped
    code, output = _clflow(*args, "--retry-failed", env=cluster.env)
    assert code == 0 and "3 run(s) finished earlier, skipped" in output and "4 of 4 runs ok" in output, output

    code, output = _clflow("sweep", spec, "-o", tmp_path / "serial", "--serial", env=cluster.env)
    assert code == 0, output
    on_cluster, serial = _results(out), _results(tmp_path / "serial")
    assert on_cluster.keys() == serial.keys()
    for name, record in serial.items():
        arrays = record.pop("arrays")
        other = on_cluster[name].pop("arrays")
        assert on_cluster[name] == record, name
        for key, value in arrays.items():
            np.testing.assert_array_equal(other[key], value, err_msg=f"{name}: {key}")


@pytest.mark.slow
def test_runs_that_no_node_left_can_run_are_recorded_as_failed_not_waited_for(cluster, quick_demo, tmp_path):
    """The only node with the resource the runs ask for dies: its run is killed, the next is
    recorded as failed once no node has come back for NO_ROOM_GRACE_S (Ray would queue it forever)."""
    spec = _spec(tmp_path, quick_demo, [2.0e3, 4.0e3])
    cluster.start({}, head=True)
    only = cluster.start({"far": 1})
    out = tmp_path / "out"
    code, output = _kill_mid_sweep(
        cluster, only, "sweep", spec, "-o", out, "--address", cluster.address, "--resources", "far=1"
    )
    assert code == 1 and "0 of 2 runs ok" in output, output
    records = sorted(json.loads((out / "sweep.json").read_text())["runs"].values(), key=lambda r: r["status"])
    assert [r["status"] for r in records] == ["failed", "killed"], records
    assert records[0]["reason"].startswith("no node of the Ray cluster can run its task any more"), records[0]
    assert "NodeDiedError" in records[1]["reason"], records[1]
