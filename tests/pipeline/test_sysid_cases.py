"""``clflow eval sysid --cases FILE``: a benchmark users extend with cases of their own, in
the table's terms, without registering them in the code."""

import dataclasses
import json
import re

import pytest
from click.testing import CliRunner

from clflow.errors import InputError
from clflow_cli.main import cli
from clflow_datasets import per_class, sysid, sysid_cases, sysid_report
from tests.pipeline.test_sysid import TINY, main_table_rows

CASE_FILE = """
jelly:
  shape: sphere
  size: 0.3
  lift: 0.1
  spread: 1.0
  material: elastic
  truth: {E: 4.0e4, poissons_ratio: 0.25}
  guess: {E: 2.0e5}
  optimize: [E]
  velocity: [0.5, 0.0, 0.0]
dough:
  material: plasticine
  truth: {youngs_modulus: 1.0e5, poissons_ratio: 0.3, yield_stress: 2.0e3}
  guess: {youngs_modulus: 1.0e4, poissons_ratio: 0.3, yield_stress: 5.0e3}
"""


def test_a_case_file_gives_cases_in_the_tables_terms_run_with_the_benchmarks_policy(tmp_path):
    path = tmp_path / "cases.yaml"
    path.write_text(CASE_FILE)
    cases = sysid_cases.load_cases(path)
    jelly = cases["jelly"]
    assert (jelly.shape, jelly.size, jelly.lift, jelly.material, jelly.velocity) == (
        "sphere",
        0.3,
        0.1,
        "elastic",
        (0.5, 0.0, 0.0),
    )
    assert jelly.truth == {"youngs_modulus": 4.0e4, "poissons_ratio": 0.25}  # the alias E made canonical
    assert jelly.optimize == ("youngs_modulus",) and jelly.guess == {"youngs_modulus": 2.0e5}
    assert cases["dough"].optimize == ("youngs_modulus", "poissons_ratio", "yield_stress")  # default: the truth's
    assert jelly.method == "levenberg_marquardt" and jelly.starts == 3 and jelly.search == 24  # the policy


@pytest.mark.parametrize(
    "text, message",
    [
        ("a: {material: slime, truth: {E: 1.0}, guess: {E: 2.0}}", "slime"),
        ("a: {material: elastic, truth: {stickiness: 1.0}, guess: {stickiness: 2.0}}", "stickiness"),
        ("a: {material: elastic, truth: {E: -5.0}, guess: {E: 2.0}}", "truth is out of range"),
        ("a: {material: elastic, truth: {E: 1.0e4, nu: 0.3}, guess: {E: 2.0e4}}", "guess gives each a start"),
        ("a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, colour: red}", "a.colour: unknown key"),
        ("a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, shape: teapot}", "a.shape: must be one of cube"),
        ("a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, velocity: [1, 2]}", "a.velocity: must be a"),
        ("torus: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}}", "not one of the built-in cases"),
        ("a: {material: elastic}\na: {material: sand}", "a (line 2): duplicate key"),
        ("- just a list", "a mapping of case names"),
        # values checked as the scene config checks its own (they failed late, naming a generated file)
        (
            "a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, size: 0}",
            "a.size: must be in (0, 10000], got 0",
        ),
        ("a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, density: 0}", "a.density: must be > 0, got 0"),
        ("a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, density: 1.0e+7}", "a.density: density (rho)"),
        (
            "a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, lift: -1}",
            "a.lift: must be in [0, 10000], got -1",
        ),
        # numbers beyond what they can mean (a traceback, or an error from deep in the run, before)
        (
            "a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, size: 1.0e+308}",
            "a.size: must be in (0, 10000]",
        ),
        (
            "a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, spread: 1.0e+308}",
            "a.spread: must be in [0, 1000]",
        ),
        (
            "a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, velocity: [1.0e+308, 0, 0]}",
            "a.velocity: must be 3 numbers in [-10000, 10000]",
        ),
        (
            "a: {material: elastic, truth: {E: 1" + "0" * 400 + "}, guess: {E: 2.0e4}}",
            "a.truth.E: an integer of 401 digits is beyond any value a config takes",
        ),
        ("a: {material: elastic, truth: {E: 1.0e4}, guess: {E: 2.0e4}, optimize: E}", "a.optimize: must be a list"),
        ("a: {material: elastic, truth: {E: 1.0e4}}", "a.guess: is required"),
        # files that do not parse: one line saying where (a traceback before)
        ("a:\n  size: [0.5\n", "cases.yaml: not valid YAML: line 3, column 1: expected ',' or ']'"),
    ],
)
def test_a_bad_case_file_is_one_line_before_any_work(tmp_path, text, message):
    path = tmp_path / "cases.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=re.escape(message)):
        sysid_cases.load_cases(path)
    result = CliRunner().invoke(cli, ["eval", "sysid", "--cases", str(path), "-o", str(tmp_path / "out")])
    assert result.exit_code == 1 and message in result.output and "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_cases_of_a_file_run_and_the_table_leaves_the_published_columns_out(tmp_path):
    path = tmp_path / "cases.yaml"
    path.write_text(CASE_FILE)
    jelly = sysid_cases.load_cases(path)["jelly"]
    cases = {"jelly": dataclasses.replace(jelly, search=3, refine=0, starts=1)}  # seconds, not minutes
    summary = sysid.evaluate(["jelly"], tmp_path / "out", sysid.Settings(resolution=TINY), cases=cases)
    record = summary["cases"]["jelly"]
    assert record["status"] == "ok" and set(record["parameters"]) == {"youngs_modulus"}
    assert record["parameters"]["youngs_modulus"]["truth"] == 4.0e4
    assert record["generation"]["definition"]["velocity"] == [0.5, 0.0, 0.0]  # the file's case was made
    table = (tmp_path / "out" / "sysid.md").read_text()
    assert "| jelly | elastic |" in table and "RE/EPE" not in table and "nan" not in table.lower()
    assert "No published rows: the paper has none of these cases." in table
    rows = main_table_rows(table)
    assert len({row.count("|") for row in rows}) == 1  # every row as wide as the header
    assert json.loads((tmp_path / "out" / "sysid.json").read_text())["cases"]["jelly"] == record


def test_a_table_of_some_published_cases_averages_the_published_rows_it_shows():
    ok = {"status": "ok", "material": "elastic", "parameters": {}, "mean_re": 0.1, "epe_px": 0.2, "floor_epe_px": 0.2,
          "final_loss": 1.0, "truth_loss": 1.0, "iterations": 1, "seconds": 1.0}  # fmt: skip
    settings = sysid.settings_record(sysid.Settings())
    table = sysid_report.markdown({"settings": settings, "cases": {"torus": ok, "bird": ok}})
    mean_row = next(line for line in table.splitlines() if line.startswith("| **mean**"))
    assert "0.07/0.57" in mean_row  # PAC-NeRF: torus 0.06/0.52, bird 0.08/0.62
    assert "their means over the cases shown" in table


def test_the_table_gives_each_range_marks_a_miss_and_counts_the_ranges_that_hold():
    def param(found, low, high, truth):
        entry = {"low": low, "high": high}
        return {"found": found, "truth": truth, "guess": 1.0, "re": abs(found - truth) / truth,
                "range": [low, high], "holds_truth": sysid_report.holds(entry, truth)}  # fmt: skip

    record = {"status": "ok", "material": "plasticine", "mean_re": 0.2, "epe_px": 0.2, "floor_epe_px": 0.2,
              "final_loss": 1.0, "truth_loss": 1.0, "iterations": 1, "seconds": 1.0,
              "parameters": {"youngs_modulus": param(1.0e6, 8.5e5, 1.2e6, 2.0e6),
                             "yield_stress": param(1.5e4, 1.3e4, None, 1.54e4)}}  # fmt: skip
    summary = {"settings": sysid.settings_record(sysid.Settings()), "cases": {"clay": record}}
    assert sysid_report.coverage(summary["cases"]) == (1, 2)
    table = sysid_report.markdown(summary)
    assert "youngs_modulus: 1e+06 [8.5e+05, 1.2e+06] **misses** (2e+06)" in table
    assert "yield_stress: 1.5e+04 [1.3e+04, -] (1.54e+04)" in table
    assert "| 90 % ranges holding the truth | | 1 of 2 (50 %; 1 bounded on both sides, 0 on neither) |" in table
    rows = main_table_rows(table)
    assert len({row.count("|") for row in rows}) == 1


def test_the_table_gives_per_class_errors_as_the_peers_do_and_the_bounded_ranges_mean():
    """log10 errors for moduli, plain ones for Poisson's ratio, degrees for the friction angle,
    averaged per class, beside GIC's and ProJo4D's figures; the mean RE over the ranges bounded
    on both sides and their median width in decades."""

    def param(found, truth, low, high):
        return {"found": found, "truth": truth, "guess": 1.0, "re": abs(found - truth) / truth,
                "range": [low, high], "holds_truth": sysid_report.holds({"low": low, "high": high}, truth)}  # fmt: skip

    def case(material, **params):
        return {"status": "ok", "material": material, "mean_re": 0.1, "epe_px": 0.2, "floor_epe_px": 0.2,
                "final_loss": 1.0, "truth_loss": 1.0, "iterations": 1, "seconds": 1.0, "parameters": params}  # fmt: skip

    cases = {
        "a": case("elastic", youngs_modulus=param(1e6, 1e5, 1e5, 1e7), poissons_ratio=param(0.35, 0.3, None, 0.4)),
        "b": case("elastic", youngs_modulus=param(1e5, 1e5, 1e4, 1e5), poissons_ratio=param(0.2, 0.3, 0.1, 0.4)),
        "c": case("sand", friction_angle=param(37.5, 40.0, 30.0, 45.0)),
    }
    table = per_class.per_class(cases)
    assert table["elastic"]["youngs_modulus"] == {
        "kind": "log10",
        "error": 0.5,
        "cases": 2,
        "GIC": 0.189,
        "ProJo4D": 0.087,
    }
    assert table["elastic"]["poissons_ratio"]["kind"] == "abs"
    assert abs(table["elastic"]["poissons_ratio"]["error"] - 0.075) < 1e-12
    assert table["sand"]["friction_angle"] == {"kind": "deg", "error": 2.5, "cases": 1, "GIC": 6.785, "ProJo4D": 0.903}
    bounded = per_class.bounded_ranges(cases)
    assert bounded["parameters"] == 4  # poissons_ratio of "a" is open below
    assert abs(bounded["mean_re"] - (9.0 + 0.0 + 1 / 3 + 0.0625) / 4) < 1e-12
    assert abs(bounded["median_width_decades"] - (1.0 + 0.6020599913) / 2) < 1e-9  # widths 2, 1, 0.602, 0.176
    text = sysid_report.markdown({"settings": sysid.settings_record(sysid.Settings()), "cases": cases})
    assert "| sand | friction_angle (deg) | 2.5 | 1 | 6.785 | 0.903 |" in text
    assert "| mean over the 4 ranges bounded on both sides | | median width 0.80 decades | 2.349 |" in text
    assert "a guide to the scale, not a same-data comparison" in text


def test_the_extra_set_covers_every_material_with_guesses_either_side_and_a_thrown_case():
    from clflow.materials import MATERIALS

    extra = sysid_cases.load_cases(sysid_cases.EXTRA_CASES_FILE)
    single = {n: c for n, c in extra.items() if not isinstance(c, sysid.SceneCase)}
    assert len(single) >= 9 and not set(extra) & set(sysid_cases.CASES)
    assert {c.material for c in single.values()} == set(MATERIALS)
    sides = {(c.guess[n] > c.truth[n]) for c in extra.values() for n in c.optimize}
    assert sides == {True, False}
    assert any(any(c.velocity) for c in single.values())
    paper = {(c.material, tuple(sorted(c.truth.items()))) for c in sysid_cases.CASES.values()}
    assert not {(c.material, tuple(sorted(c.truth.items()))) for c in single.values()} & paper
    # and two scenes of several objects: a cube dropped on a heap, a ball thrown at a block
    scenes = {n: c for n, c in extra.items() if isinstance(c, sysid.SceneCase)}
    assert {n: [(o.name, o.material) for o in c.objects] for n, c in scenes.items()} == {
        "cube_on_heap": [("heap", "sand"), ("jelly", "elastic")],
        "ball_at_block": [("block", "elastic"), ("ball", "plasticine")],
    }
    assert scenes["ball_at_block"].objects[1].velocity[0] > 0  # thrown at the block


SCENE_FILE = """
pair:
  spread: 0.3
  objects:
    - name: block
      shape: cube
      size: 0.3
      position: [0.15, 0.15, 0.0]
      material: elastic
      truth: {E: 1.0e5, nu: 0.3}
      guess: {E: 1.0e4}
      optimize: [E]
    - name: ball
      shape: sphere
      size: 0.2
      position: [-0.25, 0.2, 0.0]
      velocity: [2.0, 0.0, 0.0]
      material: plasticine
      truth: {youngs_modulus: 2.0e5, poissons_ratio: 0.3, yield_stress: 2.0e3}
      guess: {yield_stress: 2.0e4}
      optimize: [yield_stress]
"""


def test_a_case_of_several_objects_names_each_objects_parameters(tmp_path):
    path = tmp_path / "cases.yaml"
    path.write_text(SCENE_FILE)
    pair = sysid_cases.load_cases(path)["pair"]
    block, ball = pair.objects
    assert (block.name, block.shape, block.size, block.position, block.material) == (
        "block",
        "cube",
        0.3,
        (0.15, 0.15, 0.0),
        "elastic",
    )
    assert ball.velocity == (2.0, 0.0, 0.0) and ball.optimize == ("yield_stress",)
    assert pair.optimize == ("block.youngs_modulus", "ball.yield_stress")  # the alias E made canonical
    assert pair.truth["block.youngs_modulus"] == 1.0e5 and pair.guess == {
        "block.youngs_modulus": 1.0e4,
        "ball.yield_stress": 2.0e4,
    }
    assert pair.material == "elastic + plasticine" and pair.spread == 0.3
    assert pair.method == "levenberg_marquardt" and pair.starts == 3 and pair.search == 24  # the policy
    config = pair.make_config(TINY, pair.guess, optimize=True)
    assert [o["name"] for o in config["objects"]] == ["block", "ball"]
    assert config["optimize"]["parameters"] == ["block.youngs_modulus", "ball.yield_stress"]
    assert config["objects"][0]["material"]["parameters"] == {"youngs_modulus": 1.0e4, "poissons_ratio": 0.3}
    assert config["evaluation"]["ground_truth"] == pair.truth


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("  spread: 0.3\n", "  spread: 0.3\n  colour: red\n", "pair.colour: unknown key"),
        ("      position: [0.15, 0.15, 0.0]\n", "", "pair.objects[0].position: is required"),
        ("name: ball", "name: block", "pair.objects[1].name: must be a new identifier for the object, got 'block'"),
        ("[-0.25, 0.2, 0.0]", "[-0.25, 0.05, 0.0]", "pair.objects[1].position: puts the shape below the floor"),
        ("guess: {yield_stress: 2.0e4}", "guess: {yield_stress: -1.0}", "case 'pair.ball': its guess is out of range"),
        ("material: plasticine", "material: slime", "slime"),
    ],
)
def test_a_bad_case_of_several_objects_is_one_line(tmp_path, old, new, message):
    path = tmp_path / "cases.yaml"
    path.write_text(SCENE_FILE.replace(old, new))
    with pytest.raises(InputError, match=re.escape(message)):
        sysid_cases.load_cases(path)


def test_set_extra_runs_clflows_own_cases_and_refuses_a_case_file_beside_it(tmp_path):
    res = CliRunner().invoke(cli, ["eval", "sysid", "--set", "extra", "--case", "torus", "-o", str(tmp_path / "o")])
    assert res.exit_code != 0 and "unknown case(s) torus; the cases are soft_ball" in res.output
    path = tmp_path / "cases.yaml"
    path.write_text(CASE_FILE)
    res = CliRunner().invoke(cli, ["eval", "sysid", "--set", "extra", "--cases", str(path), "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--cases and --set extra both choose the cases" in res.output


def test_a_case_of_several_objects_runs_and_reports_each_objects_parameters(tmp_path):
    path = tmp_path / "cases.yaml"
    path.write_text(SCENE_FILE)
    pair = dataclasses.replace(sysid_cases.load_cases(path)["pair"], search=3, refine=0, starts=1)  # seconds
    summary = sysid.evaluate(["pair"], tmp_path / "out", sysid.Settings(resolution=TINY), cases={"pair": pair})
    record = summary["cases"]["pair"]
    assert record["status"] == "ok", record["status"]
    assert record["material"] == "elastic + plasticine"
    params = record["parameters"]
    assert set(params) == {"block.youngs_modulus", "ball.yield_stress"}
    assert (params["ball.yield_stress"]["object"], params["ball.yield_stress"]["material"]) == ("ball", "plasticine")
    assert params["block.youngs_modulus"]["truth"] == 1.0e5 and "holds_truth" in params["block.youngs_modulus"]
    generation = record["generation"]  # the truth twice as fine as the optimiser's model
    assert generation["truth_grid_resolution"] - 1 == 2 * (generation["grid_resolution"] - 1)
    assert generation["truth_image"] == 2 * generation["image"]
    case = tmp_path / "out" / "cases" / "pair"
    results = json.loads((case / "results" / "params.json").read_text())
    assert set(results["objects"]) == {"block", "ball"}
    # the per-class table counts each parameter under its object's material
    assert set(summary["per_class"]) == {"elastic", "plasticine"}
    assert "block.youngs_modulus" in (tmp_path / "out" / "sysid.md").read_text()
