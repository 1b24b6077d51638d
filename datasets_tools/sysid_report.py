"""The tables of the system-identification benchmark's results: ``sysid.md`` in the layout
of the PhysFlow paper's Table 3, the published rows beside ours, the summary rows, the
coverage of the parameters' ranges and the settings and provenance lines under the table."""

from __future__ import annotations

import statistics

from clflow_datasets import per_class
from clflow_datasets.degradation import Degradation

# Table 3 of the PhysFlow paper (CVPR 2025): (mean RE, EPE px) per case and method; their
# images are 800 x 800 px, so their EPE is not comparable with ours in pixels.
# a table, one case a row: kept as written
# fmt: off
PUBLISHED: dict[str, dict[str, tuple[float, float]]] = {
    "droplet": {"PAC-NeRF": (0.06, 0.28), "GIC": (0.41, 0.42), "PhysFlow": (0.02, 0.08)},
    "letter": {"PAC-NeRF": (0.26, 0.11), "GIC": (0.02, 0.07), "PhysFlow": (0.46, 0.13)},
    "cream": {"PAC-NeRF": (3.04, 0.61), "GIC": (0.21, 0.20), "PhysFlow": (0.54, 0.64)},
    "toothpaste": {"PAC-NeRF": (0.42, 0.15), "GIC": (0.11, 0.07), "PhysFlow": (0.24, 0.16)},
    "torus": {"PAC-NeRF": (0.06, 0.52), "GIC": (0.01, 0.24), "PhysFlow": (0.51, 1.04)},
    "bird": {"PAC-NeRF": (0.08, 0.62), "GIC": (0.04, 0.36), "PhysFlow": (0.31, 0.69)},
    "playdoh": {"PAC-NeRF": (0.37, 0.55), "GIC": (0.10, 0.16), "PhysFlow": (0.15, 0.29)},
    "cat": {"PAC-NeRF": (0.31, 0.34), "GIC": (0.02, 0.08), "PhysFlow": (0.34, 0.24)},
    "trophy": {"PAC-NeRF": (0.10, 3.30), "GIC": (0.05, 1.85), "PhysFlow": (0.01, 1.33)},
}
# fmt: on
PUBLISHED_MEAN = {"PAC-NeRF": (0.52, 0.72), "GIC": (0.11, 0.38), "PhysFlow": (0.29, 0.51)}
METHODS = ("PAC-NeRF", "GIC", "PhysFlow")


def holds(entry: dict, truth: float) -> bool:
    """Whether a parameter's range (Diagnostics.ranges: low, high; None for an open end) holds ``truth``."""
    return (entry["low"] is None or truth >= entry["low"]) and (entry["high"] is None or truth <= entry["high"])


def coverage(cases: dict) -> tuple[int, int]:
    """(parameters whose range holds the truth, parameters) over the finished cases."""
    params = [p for r in cases.values() if r.get("status") == "ok" for p in r["parameters"].values()]
    return sum(bool(p.get("holds_truth")) for p in params), sum("holds_truth" in p for p in params)


def range_shapes(cases: dict) -> tuple[int, int]:
    """(ranges bounded on both sides, ranges open on both) over the finished cases: an open
    range holds any truth, so coverage is read beside these."""
    ranges = [
        p["range"] for r in cases.values() if r.get("status") == "ok" for p in r["parameters"].values() if "range" in p
    ]
    return sum(None not in r for r in ranges), sum(r == [None, None] for r in ranges)


def _fmt(value: float) -> str:
    return f"{value:.3g}"


def _caveat(name: str, record: dict) -> str:
    """What a case's identifiability check says of a parameter, for the table."""
    ident = record.get("identifiability", {})
    if name in ident.get("unresolved", []):
        values = ident["profile"][name]["values"]
        return f" (loss flat from {_fmt(min(values))} to {_fmt(max(values))})"
    notes = ["weakly constrained"] if name in ident.get("weakly_constrained", []) else []
    if name in ident.get("grid_sensitive", []):
        notes.append(f"grid-sensitive, {ident['grid_shift_z'][name]:+.2f} on {ident['grids'][0]} nodes")
    p = record.get("parameters", {}).get(name, {})
    if p.get("decided_by", "video") != "video":  # optimize.prior moved it within its range
        notes.append(f"{p['decided_by']}: the video's own {_fmt(p['video_fit'])}, RE {p['video_re']:.3f}")
    return f" ({'; '.join(notes)})" if notes else ""


def markdown(summary: dict) -> str:
    """The results as a Markdown table in the layout of the paper's Table 3, with the
    published rows (RE / EPE) beside ours where the paper has the case, and each case's loss
    found against the loss at its ground truth (below it: the model's own minimum lies
    elsewhere; above: the optimiser stopped short)."""
    cases = summary["cases"]
    methods = METHODS if any(name in PUBLISHED for name in cases) else ()
    lines = [
        "| case | material | parameter: found (truth) | RE | EPE px (floor) | loss found / at truth | iterations, "
        "main grid | seconds |" + "".join(f" {m} RE/EPE |" for m in methods),
        "|---" * (8 + len(methods)) + "|",
    ]
    for name, r in cases.items():
        published = "".join(f" {_published(PUBLISHED.get(name, {}).get(m))} |" for m in methods)
        if r.get("status") != "ok":
            lines.append(
                f"| {name} | {r['material']} | {r['status']} | - | - | - | - | {r.get('seconds', 0):.0f} |{published}"
            )
            continue
        params = "<br>".join(
            f"{n}: {_fmt(p['found'])} {_range(p)} ({_fmt(p['truth'])}), RE {p['re']:.3f}{_caveat(n, r)}"
            for n, p in r["parameters"].items()
        )
        if "time_scale" in r:  # the video's clock, fitted beside the material: not in its mean RE
            p = r["time_scale"]
            params += f"<br>time_scale: {_fmt(p['found'])} {_range(p)} ({_fmt(p['truth'])}), RE {p['re']:.3f}"
        lines.append(
            f"| {name} | {r['material']} | {params} | {r['mean_re']:.3f} | {r['epe_px']:.3f} "
            f"({r['floor_epe_px']:.3f}) | {r['final_loss']:.3g} / {r['truth_loss']:.3g} | {r['iterations']}"
            f"{_grid(r)} | {r['seconds']:.0f} |{published}"
        )
    lines += _summary_rows(cases, methods)
    return "\n".join(lines + per_class.markdown(cases) + _closing(summary, methods)) + "\n"


def _grid(r: dict) -> str:
    """A case's main grid for the table's iterations column, " on N nodes" (empty for results
    made before it was recorded)."""
    return f" on {r['grid']['main']} nodes" if "grid" in r else ""


def _range(p: dict) -> str:
    """A parameter's range for the table, "[low, high]" ("-" for an open end), marked where
    it misses the truth; empty for results made before ranges."""
    if "range" not in p:
        return ""
    low, high = ("-" if v is None else _fmt(v) for v in p["range"])
    return f"[{low}, {high}]" + ("" if p["holds_truth"] else " **misses**")


def _published(row: tuple[float, float] | None) -> str:
    return "-" if row is None else f"{row[0]:.2f}/{row[1]:.2f}"


def _summary_rows(cases: dict, methods: tuple[str, ...]) -> list[str]:
    """The mean and median rows over the finished cases; the published means are the paper's
    for its nine, else the means of the rows shown (cases the paper lacks left out)."""
    ok = [r for r in cases.values() if r.get("status") == "ok"]
    if not ok:
        return []
    if set(cases) == set(PUBLISHED):
        means = {m: PUBLISHED_MEAN[m] for m in methods}
    else:
        rows = [PUBLISHED[name] for name in cases if name in PUBLISHED]
        means = {m: tuple(statistics.fmean(row[m][k] for row in rows) for k in (0, 1)) for m in methods}
    total = sum(r.get("seconds", 0.0) for r in cases.values())
    mean_re, mean_epe = sum(r["mean_re"] for r in ok) / len(ok), sum(r["epe_px"] for r in ok) / len(ok)
    bounded = per_class.bounded_ranges(cases)
    bounded_row = (
        [
            f"| mean over the {bounded['parameters']} ranges bounded on both sides | | median width "
            f"{bounded['median_width_decades']:.2f} decades | {bounded['mean_re']:.3f} | | | | |" + " |" * len(methods)
        ]
        if bounded["parameters"] and bounded["median_width_decades"] is not None
        else []
    )
    from clflow.pipeline.fit.diagnostics import RANGE_LEVEL

    held, counted = coverage(cases)
    bounded, unbounded = range_shapes(cases)
    ranges = [
        f"| {100 * RANGE_LEVEL:.0f} % ranges holding the truth | | {held} of {counted} ({100 * held / max(counted, 1):.0f} %; "
        f"{bounded} bounded on both sides, {unbounded} on neither) | | | | | |" + " |" * len(methods)
    ]
    return (ranges if counted else []) + [
        f"| **mean** ({len(ok)} of {len(cases)}) | | | **{mean_re:.3f}** | **{mean_epe:.3f}** | | | {total:.0f} |"
        + "".join(f" {_published(means[m])} |" for m in methods),
        f"| median | | | {statistics.median(r['mean_re'] for r in ok):.3f} | "
        f"{statistics.median(r['epe_px'] for r in ok):.3f} | | | |" + " |" * len(methods),
        *bounded_row,
        *_video_alone_row(ok, methods),
    ]


def _video_alone_row(ok: list[dict], methods: tuple[str, ...]) -> list[str]:
    """With optimize.prior: the mean RE of the video's own fits (before the prior's move), the
    same runs', and how many parameters the prior decided; [] without."""
    if not any("video_re" in p for r in ok for p in r["parameters"].values()):
        return []
    alone = [statistics.fmean(p.get("video_re", p["re"]) for p in r["parameters"].values()) for r in ok]
    decided = sum(p.get("decided_by", "video") != "video" for r in ok for p in r["parameters"].values())
    return [
        f"| mean from the video alone (the fits before the prior; it decided {decided} parameters) | | | "
        f"{statistics.fmean(alone):.3f} | | | | |" + " |" * len(methods)
    ]


def _main_phase(settings: dict) -> str:
    """The main phase's grid in the settings line: its scale, or the budget that chose it."""
    if settings.get("case_budget") is None:
        return f"{settings['resolution'].get('main_grid_scale', 1.0):g}x"
    return f"the finest a budget of {settings['case_budget']:g} s per case affords, timed on the device"


def _closing(summary: dict, methods: tuple[str, ...]) -> list[str]:
    """The settings and provenance lines under the table."""
    s = summary["settings"]
    res = s["resolution"]
    env = summary.get("environment", {})
    if not methods:
        published = "No published rows: the paper has none of these cases."
    elif set(summary["cases"]) == set(PUBLISHED):
        published = "Published rows: PhysFlow (CVPR 2025) Table 3, 800 x 800 px images."
    else:
        published = (
            "Published rows: PhysFlow (CVPR 2025) Table 3, 800 x 800 px images; their means over the cases shown."
        )
    return [
        "",
        f"Settings: grid {res['grid']} nodes (search; main phase {_main_phase(s)}), "
        f"PIC/FLIP blend {res.get('flip', 0.0):g}, "
        f"image {res['image']} px, {res['frames']} frames, "
        f"{res['iterations']} iterations; ground truth at {s['truth_scale']}x grid and image; noise "
        f"{s['noise']} grey levels; codec {s['codec'] or 'none (PNG)'}; "
        + _artefacts(Degradation(**s.get("degradation", {})))
        + f"seed {s['seed']}; "
        f"{s.get('views', 1)} guidance view{'s' if s.get('views', 1) > 1 else ''}"
        + (
            "; optimize.prior knowledge (the knowledge base decides what the video leaves weakly constrained)"
            if s.get("prior") == "knowledge"
            else ""
        )
        + (
            "; ground truth under APIC, a transfer the optimiser does not share."
            if s.get("truth_transfer") == "apic"
            else "."
        ),
        f"Made {env.get('date', '?')} with clflow {env.get('clflow', '?')} (commit {env.get('commit') or '?'}), "
        f"torch {env.get('torch', '?')}, "
        f"pyopencl {env.get('pyopencl', '?')} on {env.get('device', '?')} (load {env.get('load', '?')}). " + published,
    ]


def _artefacts(degradation: Degradation) -> str:
    """The settings line's words for a degraded guidance ("" for a clean one)."""
    return "" if degradation == Degradation() else f"artefacts: {degradation.describe()}; "


__all__ = [
    "METHODS",
    "PUBLISHED",
    "PUBLISHED_MEAN",
    "coverage",
    "holds",
    "markdown",
]
