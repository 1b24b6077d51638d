"""The optimisation history plot: loss panel with phases and horizon, a panel per parameter."""

import numpy as np

from clflow.fileio import WRITTEN_RECORD
from clflow.pipeline.plots import history_figure, write_history_plot


def history():
    rows = []
    for i in range(12):
        phase = "velocity" if i < 3 else "main"
        frames = 2 if i < 3 else 4 + 2 * ((i - 3) // 4)  # 4, 6, 8: the horizon grows twice
        rows.append(
            {
                "iteration": i,
                "phase": phase,
                "loss": 0.5 * 0.8**i,
                "frames": frames,
                "params": {"youngs_modulus": 1e4 * 1.3**i, "poissons_ratio": 0.3, "velocity_x": 0.01 * i},
            }
        )
    return rows


def test_history_figure_panels_scales_truth_and_horizon():
    fig = history_figure(history(), {"youngs_modulus": 1e5, "velocity_x": 0.1})
    loss, *params = fig.axes
    assert [a.get_ylabel().split(" (")[0] for a in params] == ["poissons_ratio", "youngs_modulus", "velocity_x"]
    assert [a.get_ylabel() for a in params] == [
        "poissons_ratio (dimensionless)",
        "youngs_modulus (Pa)",
        "velocity_x (m/s)",
    ]
    assert loss.get_yscale() == "log" and [a.get_yscale() for a in params] == ["linear", "log", "linear"]
    assert params[-1].get_xlabel() == "iteration"
    legend = [t.get_text() for t in loss.get_legend().get_texts()]
    assert legend == ["velocity phase", "main phase", "horizon grows to N frames"]
    phase_lines = loss.get_lines()[:2]
    assert phase_lines[0].get_color() != phase_lines[1].get_color()
    np.testing.assert_array_equal(phase_lines[1].get_xdata(), np.arange(3, 12))
    horizon = [line.get_xdata()[0] for line in loss.get_lines()[2:]]
    assert horizon == [2.5, 6.5, 10.5]  # where frames goes 2 -> 4 -> 6 -> 8
    assert [t.get_text() for t in loss.texts] == ["2 frames", "4", "6", "8"]  # the first horizon, then each growth
    truth = [line for line in params[1].get_lines() if line.get_linestyle() == "--"]
    assert len(truth) == 1 and truth[0].get_ydata()[0] == 1e5
    assert params[0].get_legend() is None  # no truth for poissons_ratio


def test_write_history_plot_writes_a_png(tmp_path):
    from PIL import Image

    write_history_plot(tmp_path / "loss.png", history(), {})
    with Image.open(tmp_path / "loss.png") as image:
        assert image.format == "PNG" and image.height > image.width > 500
    assert sorted(p.name for p in tmp_path.iterdir()) == [WRITTEN_RECORD, "loss.png"]


def test_each_parameters_range_is_a_band_an_open_end_running_to_the_panels_edge():
    ranges = {
        "youngs_modulus": {"low": 2e4, "high": 9e4, "level": 0.9},
        "poissons_ratio": {"low": 0.25, "high": None, "level": 0.9},
    }
    fig = history_figure(history(), {"youngs_modulus": 1e5}, ranges)
    poisson, young, velocity = fig.axes[1:]
    (band,) = young.patches
    assert band.get_y() == 2e4 and band.get_y() + band.get_height() == 9e4
    legend = [t.get_text() for t in young.get_legend().get_texts()]
    assert legend == ["truth 1e+05", "90 % range: 2e+04 - 9e+04"]
    (open_band,) = poisson.patches
    assert open_band.get_y() == 0.25 and open_band.get_y() + open_band.get_height() == poisson.get_ylim()[1]
    assert [t.get_text() for t in poisson.get_legend().get_texts()] == ["90 % range: >= 0.25"]
    assert not velocity.patches and velocity.get_legend() is None


def test_a_range_in_words():
    from clflow.pipeline.plots import range_text

    assert range_text({"low": 1.2e5, "high": 3.4e5}, "Pa") == "1.2e+05 - 3.4e+05 Pa"
    assert range_text({"low": 2.1e5, "high": None}, "Pa") == ">= 2.1e+05 Pa"
    assert range_text({"low": None, "high": 40.0}, "1") == "<= 40"
    assert range_text({"low": None, "high": None}) == "not bounded"
