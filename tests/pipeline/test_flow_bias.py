"""`clflow bench flow-bias`: the observed flow's bias at the ground truth, measured."""

from click.testing import CliRunner

from clflow_cli.main import cli


def test_the_full_resolution_preset_is_the_less_biased_on_the_quick_demo():
    result = CliRunner().invoke(
        cli,
        [
            "bench",
            "flow-bias",
            "--case",
            "cube",
            "--preset",
            "medium",
            "--preset",
            "fine",
            "--confidence",
            "forward_backward",
            "--iterations",
            "0",
        ],
        catch_exceptions=False,
    )
    assert result.exit_code == 0, result.output
    # case preset confidence slope EPE kept youngs_modulus RE-at-min; RE-recovered
    rows = {line.split()[1]: line.split() for line in result.output.splitlines() if line.startswith("cube ")}
    slope = {preset: float(row[3]) for preset, row in rows.items()}
    epe = {preset: float(row[4]) for preset, row in rows.items()}
    at_minimum = {preset: float(row[7].rstrip("%;")) / 100 for preset, row in rows.items()}
    # fine is the less biased: a slope near 1 and a smaller error of E at the loss minimum than
    # medium, whose DIS at half resolution blends the cube with the floor (the figures: docs/flow.md,
    # "Observed-flow bias")
    assert 0.95 < slope["fine"] < 1.03 and slope["medium"] < slope["fine"]
    assert epe["fine"] < epe["medium"]
    assert abs(at_minimum["fine"]) < 0.06 and abs(at_minimum["fine"]) < 0.6 * abs(at_minimum["medium"])
