"""Plots of an optimisation (matplotlib figures drawn by Agg: no display, no pyplot state).

    write_history_plot("results/loss.png", history, truth)
    fig = history_figure(history, truth)      # to inspect or save elsewhere

``history`` holds the optimiser's rows (``iteration``, ``phase``, ``loss``, ``frames`` and
``params``: see clflow.pipeline.fit); ``truth`` the ground-truth values when known.
"""

from __future__ import annotations

from pathlib import Path

from clflow.fileio import atomic_path
from clflow.materials import DENSITY, MATERIALS
from clflow.scene.config import TIME_SCALE, is_velocity_component

#: Colour and marker of each optimiser phase (another phase gets the next default colour).
PHASE_STYLE = {"velocity": ("tab:orange", "s"), "search": ("tab:green", "^"), "main": ("tab:blue", "o")}
#: Loss axis label: flow.loss l2 is in px^2, charbonnier in px.
LOSS_LABEL = "flow loss per frame and pixel\n(px² for l2, px for Charbonnier)"


def _parameter_axis(name: str) -> tuple[str, bool]:
    """(axis label with unit, whether the axis is logarithmic) of an optimised variable (with
    several objects OBJECT.PARAM)."""
    if is_velocity_component(name):
        return f"{name} (m/s)", False
    params = {p.name: p for material in MATERIALS.values() for p in material.params}
    params |= {DENSITY.name: DENSITY, TIME_SCALE.name: TIME_SCALE}
    param = name.rpartition(".")[2]
    if param not in params:
        return name, False
    p = params[param]
    return f"{name} ({'dimensionless' if p.unit == '1' else p.unit})", p.scale == "log"


def write_history_plot(
    path: Path, history: list[dict], truth: dict[str, float], ranges: dict[str, dict] | None = None
) -> None:
    """:func:`history_figure` as a PNG, written atomically."""
    with atomic_path(path) as tmp:
        history_figure(history, truth, ranges).savefig(tmp, format="png", dpi=110)


def _plot_by_phase(axis, history: list[dict], phases: list[str], style: dict, value, labelled: bool = False):
    """``value(row)`` against iteration, a line per phase in its colour and marker."""
    for phase in phases:
        rows = [h for h in history if h["phase"] == phase]
        colour, marker = style[phase]
        axis.plot(
            [h["iteration"] for h in rows],
            [value(h) for h in rows],
            color=colour,
            marker=marker,
            markersize=3,
            linewidth=1.2,
            label=f"{phase} phase" if labelled else None,
        )


def _mark_horizons(axes, history: list[dict]) -> bool:
    """Each change of the loss horizon as a dotted line in every panel and its frame count
    over the first (the first horizon labelled too, "N frames", without a line); True if it
    changed."""
    changes = [row for before, row in zip(history, history[1:]) if row["frames"] != before["frames"]]
    for row in history[:1] + changes:
        x = row["iteration"] - 0.5
        for axis in axes if row is not history[0] else ():
            axis.axvline(x, color="grey", linestyle=":", linewidth=0.8)
        axes[0].annotate(
            f"{row['frames']} frames" if row is history[0] else f"{row['frames']}",
            (x, 1.0),
            xycoords=("data", "axes fraction"),
            fontsize=7,
            color="dimgrey",
            ha="center",
            va="bottom",
        )
    return bool(changes)


def range_text(entry: dict, unit: str = "") -> str:
    """A range in words: "1.2e+05 - 3.4e+05 Pa", ">= 2.1e+05 Pa", "<= 40", or "not bounded"."""
    low, high, unit = entry["low"], entry["high"], f" {unit}" if unit and unit != "1" else ""
    if low is None and high is None:
        return "not bounded"
    if low is None:
        return f"<= {high:.3g}{unit}"
    return f">= {low:.3g}{unit}" if high is None else f"{low:.3g} - {high:.3g}{unit}"


def _range_band(axis, entry: dict) -> None:
    """The range as a shaded band over the whole panel, an open end running to its edge."""
    axis.autoscale_view()
    bottom, top = axis.get_ylim()
    low = bottom if entry["low"] is None else entry["low"]
    high = top if entry["high"] is None else entry["high"]
    label = f"{100 * entry['level']:.0f} % range: {range_text(entry)}"
    axis.axhspan(low, high, color="tab:green", alpha=0.15, linewidth=0, label=label)
    # a closed end stays in view with a margin; an open one runs to the panel's edge
    logarithmic = axis.get_yscale() == "log"
    pad = (lambda v, k: v * (high / low) ** (0.05 * k)) if logarithmic else (lambda v, k: v + 0.05 * k * (high - low))
    axis.set_ylim(
        min(bottom, low if entry["low"] is None else pad(low, -1)),
        max(top, high if entry["high"] is None else pad(high, 1)),
    )


def history_figure(history: list[dict], truth: dict[str, float], ranges: dict[str, dict] | None = None):
    """A matplotlib Figure: the loss per frame and pixel against iteration (log scale;
    phases in their own colours, legend in this panel only; each change of the loss
    horizon marked in every panel), then each
    parameter against iteration (log scale for log-scale parameters) with the ground truth
    as a dashed line when ``truth`` has it and the result's range (``ranges``: name ->
    {low, high, level}, SI, None for an open end; Diagnostics.ranges) as a band."""
    import matplotlib
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    names = sorted(history[0]["params"], key=lambda n: (is_velocity_component(n), n)) if history else []
    fig = Figure(figsize=(7.0, 2.6 * (1 + len(names))))
    axes = fig.subplots(1 + len(names), 1, sharex=True, squeeze=False)[:, 0]
    phases = list(dict.fromkeys(h["phase"] for h in history))
    colours = iter(matplotlib.rcParams["axes.prop_cycle"].by_key()["color"][3:])
    style = {p: PHASE_STYLE.get(p) or (next(colours), "o") for p in phases}

    loss_axis = axes[0]
    _plot_by_phase(loss_axis, history, phases, style, lambda h: h["loss"], labelled=True)
    handles = loss_axis.get_legend_handles_labels()[0]
    if _mark_horizons(axes, history):
        handles.append(Line2D([], [], color="grey", linestyle=":", label="horizon grows to N frames"))
    if history:
        loss_axis.set_yscale("log")
        loss_axis.legend(handles=handles, fontsize=8, loc="upper right")
    loss_axis.set_ylabel(LOSS_LABEL, fontsize=8)
    loss_axis.set_title("optimisation history", fontsize=10, pad=14)

    for axis, name in zip(axes[1:], names):
        label, log_scale = _parameter_axis(name)
        _plot_by_phase(axis, history, phases, style, lambda h, name=name: h["params"][name])
        if name in truth:
            axis.axhline(truth[name], color="black", linestyle="--", linewidth=1.0, label=f"truth {truth[name]:.4g}")
        if log_scale:
            axis.set_yscale("log")
        if ranges and name in ranges:
            _range_band(axis, ranges[name])
        axis.set_ylabel(label, fontsize=8)
        if name in truth or (ranges and name in ranges):
            axis.legend(fontsize=8, loc="best")
    for axis in axes:
        axis.grid(True, which="major", alpha=0.3)
        if history:
            axis.set_xlim(history[0]["iteration"] - 0.5, history[-1]["iteration"] + 0.5)
    axes[-1].set_xlabel("iteration")
    axes[-1].xaxis.set_major_locator(MaxNLocator(integer=True))
    fig.tight_layout()
    return fig
