"""The results folder as a page people open: ``index.html`` and ``run.json``.

``write_run_record(cfg, output)`` writes ``run.json``: clflow, torch, pyopencl and PoCL
versions, the OpenCL device, the git commit, the resolved config and the command line.
``write_report(output)`` writes ``index.html`` from what the folder holds (params.json,
metrics.json, hypotheses.json, loss.png, comparison.mp4, simulation/render4d/*.mp4,
run.json): self-contained, every link relative, no script or style from elsewhere, so the
folder can be zipped, served or opened from disk. Each video's duration, once the browser
has read it, is written under it (``data-duration``), which the tests read back.
"""

from __future__ import annotations

import html
import json
import sys
from pathlib import Path

from clflow.environment import environment
from clflow.fileio import atomic_write_text
from clflow.fileio.reading import parse_json
from clflow.limits import format_duration
from clflow.pipeline.plots import range_text
from clflow.scene.config import config_record

RENDERS = "simulation/render4d"  # where `clflow demo` / `clflow render4d` put the 4D renders


def write_run_record(cfg, output: Path, argv: list[str] | None = None) -> dict:
    """``output/run.json``: environment(), the resolved config ``cfg`` (a SceneConfig) and
    the command line (default sys.argv)."""
    record = {
        "environment": environment(),
        "command": list(sys.argv if argv is None else argv),
        "config": json.loads(json.dumps(config_record(cfg), default=str)),
    }
    atomic_write_text(output / "run.json", json.dumps(record, indent=2))
    return record


def _read(path: Path) -> dict | None:
    try:
        return parse_json(path.read_text())
    except (OSError, ValueError):
        return None


def _table(rows: list[tuple[str, ...]], head: tuple[str, ...]) -> str:
    cells = lambda tag, row: "".join(f"<{tag}>{html.escape(str(c))}</{tag}>" for c in row)  # noqa: E731
    return (
        f"<table><thead><tr>{cells('th', head)}</tr></thead><tbody>"
        + "".join(f"<tr>{cells('td', r)}</tr>" for r in rows)
        + "</tbody></table>"
    )


def _video(rel: str, caption: str) -> str:
    return (
        f'<figure><video src="{html.escape(rel)}" controls loop muted playsinline preload="metadata" '
        f'onloadedmetadata="this.parentNode.dataset.duration=this.duration.toFixed(3);'
        f"this.nextElementSibling.textContent+=' (' + this.duration.toFixed(2) + ' s)'\"></video>"
        f"<figcaption>{html.escape(caption)}</figcaption></figure>"
    )


STYLE = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:0.5em 0 1.5em}td,th{border:1px solid #ccc;padding:4px 10px;text-align:left}
th{background:#f3f3f3}figure{display:inline-block;margin:0 1em 1em 0;vertical-align:top}
video,img{max-width:100%;border:1px solid #ddd}figcaption{font-size:0.9em;color:#555}
.bad{color:#a00}code{background:#f3f3f3;padding:1px 4px}"""


def write_report(output: Path, staged: Path | None = None) -> Path:
    """``output/index.html`` from the results in ``output`` (see module docstring); with
    ``staged`` (a folder of new results that will move into ``output``, clflow.fileio.atomic_dir),
    those read from and the page written there. Returns where the page is."""
    output = Path(output).resolve()
    staged = output if staged is None else Path(staged)

    def at(name: str) -> Path:  # a result: the staged one, else the folder's
        return staged / name if (staged / name).exists() else output / name

    params, metrics = _read(at("params.json")), _read(at("metrics.json"))
    run = _read(at("run.json"))
    # the folder with its parent: the default output folder is a scene's "results"
    title = html.escape(f"{output.parent.name}/{output.name}" if output.parent.name else output.name)
    parts = [f"<h1>clflow results: {title}</h1>"]
    if params:
        units = params.get("units", {})
        ranges = params.get("ranges", {})
        rows = [
            (n, f"{v:.6g}", range_text(ranges[n]) if n in ranges else "", units.get(n, ""))
            for n, v in params.get("optimized", {}).items()
        ]
        objects = params.get("objects")
        if objects:  # several: each object's material, its parameters named OBJECT.PARAM
            each = ", ".join(f"{name} {entry.get('material', '?')}" for name, entry in objects.items())
            parts.append(f"<h2>Materials: {html.escape(each)}</h2>")
        else:
            parts.append(f"<h2>Material: {html.escape(params.get('material', '?'))}</h2>")
        parts.append("<h3>Optimised</h3>" + _table(rows, ("parameter", "value", "90 % range", "unit")))
        for name, entry in objects.items() if objects else [(None, params)]:
            prefix = "" if name is None else f"{name}."
            fixed = [
                (prefix + n, f"{v:.6g}")
                for n, v in entry.get("parameters", {}).items()
                if prefix + n not in params.get("optimized", {})
            ]
            fixed.append((f"{prefix}density (kg/m^3)", f"{entry.get('density', float('nan')):.6g}"))
            fixed.append((f"{prefix}initial velocity (m/s)", ", ".join(f"{v:.4g}" for v in entry.get("velocity", []))))
            title = "All parameters (SI)" if name is None else f"{name}: all parameters (SI)"
            parts.append(f"<h3>{html.escape(title)}</h3>" + _table(fixed, ("parameter", "value")))
    if metrics:
        rows = [
            ("flow loss (per frame and pixel)", f"{metrics.get('flow_loss', float('nan')):.4g}"),
            ("flow end-point error (px)", f"{metrics.get('epe_px', float('nan')):.4g}"),
            ("iterations", metrics.get("iterations", "")),
            ("seconds per iteration", f"{metrics.get('seconds_per_iteration', float('nan')):.3g}"),
        ]
        if "unexplained_motion" in metrics:  # the squared flow residual over the observed flow's own
            rows.append(("observed motion left unexplained", f"{metrics['unexplained_motion']['fraction']:.1%}"))
        rows += [("warning", line) for line in metrics.get("warnings", [])]
        if "grid" in metrics:  # nodes along the domain's longest side
            rows.append(("grid: main phase, search (nodes)", f"{metrics['grid']['main']}, {metrics['grid']['search']}"))
        if "budget" in metrics:
            budget = metrics["budget"]
            took = f"; took {format_duration(metrics['seconds'])}" if "seconds" in metrics else ""
            rows.append(
                (
                    "budget",
                    f"{format_duration(budget['budget_seconds'])}: main grid predicted "
                    f"{format_duration(budget['predicted_seconds'])}{took}",
                )
            )
        rows += [(f"relative error: {n}", f"{e:.3%}") for n, e in metrics.get("relative_error", {}).items()]
        ident = metrics.get("identifiability", {})
        rows += [(f"weakly constrained: {n}", "the video barely fixes it") for n in ident.get("weakly_constrained", [])]
        for name in ident.get("unresolved", []):
            values = ident["profile"][name]["values"]
            rise = f"loss within {100 * ident['profile_rise']:.0f} %"
            rows.append((f"unresolved: {name}", f"{rise} from {min(values):.3g} to {max(values):.3g} (SI)"))
        rows += [(f"trade-off: {a} / {b}", f"correlation {rho:.3f}") for a, b, rho in ident.get("trade_offs", [])]
        rows += [  # optimize.prior: what the material knowledge base decided, and the video's own value
            (
                f"decided by the prior: {n}",
                f"{e['value']:.4g} ({e['decided_by']}; {e['entry']}, {e['prior_range'][0]:.3g} - "
                f"{e['prior_range'][1]:.3g}); the video alone {e['video_fit']:.4g}",
            )
            for n, e in metrics.get("prior", {}).get("parameters", {}).items()
            if e["decided_by"] != "video"
        ]
        rows += [
            (
                f"grid-sensitive: {n}",
                f"fit moves {ident['grid_shift_z'][n]:+.2g} (optimiser units) on {ident['grids'][0]} nodes",
            )
            for n in ident.get("grid_sensitive", [])
        ]
        chosen = metrics.get("material_hypotheses")
        if chosen:
            rows += [
                (f"hypothesis {m}", f"best search loss {r['loss']:.4g}" if "loss" in r else "failed")
                for m, r in chosen["hypotheses"].items()
            ]
        parts.append("<h2>Metrics</h2>" + _table(rows, ("metric", "value")))
    if at("loss.png").exists():
        parts.append('<h2>Optimisation</h2><img src="loss.png" alt="loss and parameters per iteration">')
    comparisons = ["comparison.mp4", *sorted(p.name for p in staged.glob("comparison_view*.mp4"))]
    videos = [(name, f"{name.removesuffix('.mp4').replace('_', ' ')}: guidance | guidance flow | "
               "simulated flow | error | simulation") for name in comparisons]  # fmt: skip
    videos += [(f"{RENDERS}/{p.name}", f"4D render: {p.stem}") for p in sorted((output / RENDERS).glob("*.mp4"))]
    shown = [_video(rel, caption) for rel, caption in videos if at(rel).exists()]
    if shown:
        parts.append("<h2>Videos</h2>" + "".join(shown))
    if run:
        env = run.get("environment", {})
        rows = [(k, v) for k, v in env.items() if v is not None]
        rows.append(("command", " ".join(run.get("command", []))))
        parts.append(
            "<h2>Made with</h2>" + _table(rows, ("", "")) + "<p>Resolved config and all versions: "
            '<a href="run.json">run.json</a></p>'
        )
    links = [
        n for n in ("params.json", "metrics.json", "history.json", "hypotheses.json", "search.json") if at(n).exists()
    ]
    if links:
        parts.append("<p>Data: " + ", ".join(f'<a href="{n}">{n}</a>' for n in links) + "</p>")
    page = (
        f"<!doctype html><html lang=en><head><meta charset=utf-8><title>clflow results: {title}</title>"
        f"<style>{STYLE}</style></head><body>{''.join(parts)}</body></html>\n"
    )
    atomic_write_text(staged / "index.html", page)
    return staged / "index.html"


__all__ = ["environment", "write_report", "write_run_record"]  # environment: from clflow.environment
