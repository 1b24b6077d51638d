"""The sweep: each run into its own folder (finished ones of the same inputs skipped), its
record in ``result.json``, all of them in ``sweep.json`` and ``sweep.md`` as they finish."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

from clflow.fileio.reading import parse_json
from clflow.parallel import ray_session, serial_order, task_env
from clflow.sweep.runner import run_on_ray, run_serial
from clflow.sweep.spec import FINISHED, Run, Spec, inputs_of


def previous_record(folder: Path) -> dict | None:
    try:
        record = parse_json((folder / "result.json").read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("status") in FINISHED else None


def sweep(
    spec: Spec,
    out: Path,
    *,
    serial: bool = False,
    address: str | None = None,
    cpus_per_task: int = 1,
    resources: dict[str, float] | None = None,
    timeout: float | None = None,
    retry_failed: bool = False,
    device: str | None = None,
    echo: Callable[[str], None] = lambda line: None,
) -> dict:
    """Run the spec's runs into ``out`` (skipping those finished earlier with the same inputs:
    all but failed ones with ``retry_failed``), writing ``sweep.json`` and ``sweep.md`` as they
    finish; returns the summary. KeyboardInterrupt leaves the finished runs recorded."""
    from clflow.fileio import atomic_write_text, output_folder
    from clflow.limits import check_output

    out = Path(out).resolve()  # tasks run in other working folders
    check_output(out)
    runs_dir = out / "runs"

    def folder_of(run: Run) -> Path:
        return runs_dir / run.name

    summary: dict[str, Any] = {"spec": str(spec.source.resolve()), "runs": {}}
    inputs = {run.name: inputs_of(run) for run in spec.runs}  # a run's identity: its name and these
    todo = []
    for run in spec.runs:
        earlier = previous_record(folder_of(run))
        changed = earlier is not None and _changed(earlier, inputs[run.name])
        if changed:
            echo(f"run {run.name}: {changed}, running it again")
        if earlier and not changed and (earlier["status"] == "ok" or not retry_failed):
            summary["runs"][run.name] = {**earlier, "skipped": True}
        else:
            summary["runs"][run.name] = {"name": run.name, **run.params(), "status": "pending"}
            todo.append(run)

    def write() -> None:
        summary["finished"] = sum(r["status"] in FINISHED for r in summary["runs"].values())
        atomic_write_text(out / "sweep.json", json.dumps(summary, indent=2))
        atomic_write_text(out / "sweep.md", markdown(summary))

    def done(record: dict) -> None:
        record["inputs"] = inputs[record["name"]]
        record["date"] = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
        atomic_write_text(runs_dir / record["name"] / "result.json", json.dumps(record, indent=2))
        summary["runs"][record["name"]] = record
        write()
        echo(
            f"{record['name']}: {record['status']}{': ' + record['reason'] if record.get('reason') else ''} "
            f"({record['seconds']:.1f} s)"
        )

    with output_folder(out):  # this sweep's: other runs are refused
        write()
        skipped = len(spec.runs) - len(todo)
        if skipped:
            echo(
                f"{skipped} run(s) finished earlier, skipped"
                + ("" if retry_failed else " (--retry-failed reruns the failed ones)")
            )
        if not todo:
            return summary
        order = serial_order()
        summary["mode"] = "serial" if serial else f"ray ({address or 'local'}, {cpus_per_task} CPU per task)"
        try:
            if serial:  # (torch's threads: this process's)
                run_serial(todo, folder_of, timeout, done, env=order, inputs=inputs)
            else:
                with ray_session(address, instead=None):
                    run_on_ray(
                        todo,
                        folder_of,
                        timeout,
                        done,
                        env=task_env(cpus_per_task, device, order),
                        cpus_per_task=cpus_per_task,
                        resources=resources,
                        args=lambda run: (run, str(folder_of(run)), inputs[run.name]),
                    )
        finally:
            write()
        return summary


def _changed(record: dict, inputs: dict[str, str]) -> str | None:
    """How ``record``'s inputs differ from ``inputs`` (None: they do not)."""
    earlier = record.get("inputs")
    if not isinstance(earlier, dict):
        return "its result has no digest of its inputs (an earlier clflow's)"
    parts = sorted(k for k in earlier.keys() | inputs.keys() if earlier.get(k) != inputs.get(k))
    return f"its inputs changed since its result ({', '.join(parts)})" if parts else None


def markdown(summary: dict) -> str:
    """The summary as a Markdown table, one row per run."""
    runs = summary["runs"].values()
    counts = {s: sum(r["status"] == s for r in runs) for s in ("ok", "failed", "timeout", "killed", "pending")}
    lines = [
        f"# Sweep of {summary['spec']}",
        "",
        ", ".join(f"{n} {s}" for s, n in counts.items() if n) + f" of {len(summary['runs'])} runs",
        "",
        "| run | command | config / case | set | status | seconds | result or reason |",
        "|---" * 7 + "|",
    ]
    for r in runs:
        what = r.get("case") or Path(r.get("config", "")).name
        sets = "<br>".join(r.get("set", []))
        if r["status"] == "ok":
            result = r.get("result") or {}
            detail = ", ".join(
                f"{k} {_short(v)}"
                for k, v in result.items()
                if isinstance(v, (int, float, str)) and not isinstance(v, bool)
            )[:200]
        else:
            detail = (r.get("reason") or "").replace("|", "\\|")
        seconds = f"{r['seconds']:.1f}" if isinstance(r.get("seconds"), (int, float)) else "-"
        lines.append(f"| {r['name']} | {r['command']} | {what} | {sets} | {r['status']} | {seconds} | {detail} |")
    return "\n".join(lines) + "\n"


def _short(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)
