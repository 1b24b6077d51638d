"""Material hypotheses (optimize.material): each is searched, the best fitting one is optimised."""

import json

import yaml
from click.testing import CliRunner

from clflow_cli.main import cli


def hypotheses_config(quick_demo, tmp_path, materials=("elastic", "newtonian")) -> str:
    """The quick demo (an elastic jelly, E = 2e4 Pa) asked to choose among ``materials``."""
    cfg = yaml.safe_load((quick_demo / "config.yaml").read_text())
    cfg["material"]["parameters"]["youngs_modulus"] = 1.0e4  # inside the box below
    cfg["optimize"] = {
        "parameters": ["youngs_modulus", "viscosity"],
        "material": list(materials),
        # a narrow elastic well (the loss doubles at E / 2): a box the design can resolve
        "bounds": {"youngs_modulus": [5.0e3, 8.0e4], "viscosity": [1.0, 1.0e4]},
        "search": {"samples": 10},
        "iterations": 1,
    }
    path = quick_demo / f"hypotheses_{tmp_path.name}.yaml"  # beside the demo's scene and guidance
    path.write_text(yaml.safe_dump({**cfg, "output": str(tmp_path / "results")}))
    return str(path)


def test_the_elastic_demo_is_told_apart_from_a_viscous_fluid(quick_demo, tmp_path):
    config = hypotheses_config(quick_demo, tmp_path)
    res = CliRunner().invoke(cli, ["optimize", config], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "material: elastic fits best" in res.output
    results = tmp_path / "results"
    record = json.loads((results / "hypotheses.json").read_text())
    assert record["chosen"] == "elastic"
    losses = {m: r["loss"] for m, r in record["hypotheses"].items()}
    assert losses["elastic"] < 0.5 * losses["newtonian"]  # not a close call
    assert record["hypotheses"]["newtonian"]["samples"] == 10
    params = json.loads((results / "params.json").read_text())
    assert params["material"] == "elastic" and set(params["optimized"]) == {"youngs_modulus"}
    metrics = json.loads((results / "metrics.json").read_text())
    assert metrics["material_hypotheses"] == record
    assert abs(params["optimized"]["youngs_modulus"] / 2.0e4 - 1) < 0.3
    # a rerun with --resume reads every finished search instead of running it again
    before = (results / "hypotheses" / "newtonian" / "checkpoint.json").stat().st_mtime_ns
    res = CliRunner().invoke(cli, ["optimize", config, "--resume"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "search 1/10" not in res.output
    assert (results / "hypotheses" / "newtonian" / "checkpoint.json").stat().st_mtime_ns == before


def test_an_unknown_hypothesis_is_refused_before_any_work(quick_demo, tmp_path):
    config = hypotheses_config(quick_demo, tmp_path, materials=("elastic", "lava"))
    res = CliRunner().invoke(cli, ["optimize", config])
    assert res.exit_code != 0 and "optimize.material: unknown material 'lava'" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "results").exists()
