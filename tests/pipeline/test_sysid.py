"""``clflow eval sysid``: the benchmark's cases, its honesty (no inverse crime), bad input and resuming."""

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from clflow.errors import InputError
from clflow.mpm import StabilityWarning
from clflow_cli.main import cli
from clflow_datasets import sysid, sysid_report
from clflow_datasets.synthetic import Resolution, SyntheticCase, make_case
from clflow_datasets.sysid_cases import CASES, check_case

TINY = Resolution(object_detail=6, floor_side=8, image=48, grid=14, frames=3, iterations=2)


def main_table_rows(table: str) -> list[str]:
    """The rows of sysid.md's first table (the cases)."""
    return [line for line in table.split("\n\n")[0].splitlines() if line.startswith("|")]


@pytest.mark.parametrize("name", list(CASES))
def test_every_case_starts_from_a_valid_guess(name):
    check_case(name, CASES[name])  # e.g. the trophy's 10 degree friction angle (PAC-NeRF's start)
    assert set(sysid_report.PUBLISHED[name]) == set(sysid_report.METHODS)


def test_the_guidance_is_not_the_optimisers_own_forward(tmp_path):
    case = SyntheticCase(shape="sphere", lift=0.02, spread=0.75)
    config = make_case(tmp_path, case, TINY, truth_scale=2)
    truth, opt = (yaml.safe_load((tmp_path / name).read_text()) for name in ("config_truth.yaml", "config.yaml"))
    assert truth["simulation"]["grid_resolution"] - 1 == 2 * (opt["simulation"]["grid_resolution"] - 1)
    (tlo, thi), (olo, ohi) = (
        (c["simulation"]["domain"]["min"], c["simulation"]["domain"]["max"]) for c in (truth, opt)
    )
    assert tlo == olo and thi == ohi  # the same space at half the spacing, where the ground meets either grid alike
    from clflow.pipeline.forward import prepare
    from clflow.pipeline.simulation import GROUND_OFFSET
    from clflow.scene.config import load_config

    for name in ("config_truth.yaml", "config.yaml"):
        grid = prepare(load_config(tmp_path / name)).setup.grid
        cells = -grid.origin[1] / grid.dx  # the ground (y = 0) in cells above the lowest node row
        assert cells % 1 == pytest.approx(GROUND_OFFSET) and cells > 4
    assert truth["camera"]["width"] == 2 * opt["camera"]["width"] == 2 * TINY.image
    record = json.loads((tmp_path / "case.json").read_text())
    assert record["truth_grid_resolution"] != record["grid_resolution"] and record["truth_image"] != record["image"]
    assert record["clamped"] == 0 and record["wall_contacts"] == 0
    import cv2

    frame = cv2.imread(str(tmp_path / "guidance" / "000.png"))
    assert frame.shape[:2] == (TINY.image, TINY.image)  # area-downsampled to the optimiser's camera
    assert config.name == "config.yaml"


def test_a_truth_under_apic_is_a_transfer_the_optimiser_does_not_share(tmp_path):
    """--truth-transfer apic: the ground truth runs APIC (flip 0) while the optimiser keeps its
    FLIP blend; the table says so, and results of the matched truth are other settings."""
    case = SyntheticCase(shape="sphere", lift=0.02, spread=0.75)
    flip = dataclasses.replace(TINY, flip=0.99)
    make_case(tmp_path, case, flip, truth_scale=2, truth_flip=sysid.TRUTH_FLIP["apic"])
    truth, opt = (yaml.safe_load((tmp_path / name).read_text()) for name in ("config_truth.yaml", "config.yaml"))
    assert truth["simulation"].get("flip", 0.0) == 0.0 and opt["simulation"]["flip"] == 0.99
    assert json.loads((tmp_path / "case.json").read_text())["truth_flip"] == 0.0
    apic = sysid.settings_record(sysid.Settings(truth_transfer="apic"))
    assert "ground truth under APIC" in sysid_report.markdown({"settings": apic, "cases": {}})
    older = {k: v for k, v in sysid.settings_record(sysid.Settings()).items() if k != "truth_transfer"}
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "sysid.json").write_text(json.dumps({"settings": older, "cases": {}}))
    assert sysid._earlier_summary(tmp_path / "out", sysid.Settings(), force=False)["settings"] == older
    with pytest.raises(InputError, match="truth_transfer: flip -> apic"):
        sysid._earlier_summary(tmp_path / "out", sysid.Settings(truth_transfer="apic"), force=False)


def test_noise_and_codec_reach_the_optimisers_input(tmp_path):
    case = SyntheticCase(spread=0.5)
    make_case(tmp_path / "clean", case, TINY, truth_scale=1)
    make_case(tmp_path / "noisy", case, TINY, truth_scale=1, noise=4.0, codec=".avi")
    import cv2

    clean, noisy = (cv2.imread(str(tmp_path / d / "guidance" / "001.png")).astype(float) for d in ("clean", "noisy"))
    assert 3.0 < np.std(noisy - clean) < 5.0
    cfg = yaml.safe_load((tmp_path / "noisy" / "config.yaml").read_text())
    assert cfg["video"] == "guidance_coded.avi" and (tmp_path / "noisy" / "guidance_coded.avi").stat().st_size > 0


def test_a_case_with_several_views_films_one_motion_from_each_camera(tmp_path):
    from clflow.pipeline.fit import Optimization
    from clflow.scene.config import load_config

    case = SyntheticCase(shape="sphere", lift=0.02, spread=0.75)
    make_case(tmp_path, case, TINY, truth_scale=2, views=2)
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["video"] == ["guidance", "guidance_1"] and len(cfg["camera"]) == 2
    front, side = (np.subtract(c["position"], c["look_at"]) for c in cfg["camera"])
    assert np.linalg.norm(front) == pytest.approx(np.linalg.norm(side), rel=1e-6)
    assert abs(front[0] * side[0] + front[2] * side[2]) < 1e-6  # turned 90 degrees about the vertical
    import cv2

    first, second = (cv2.imread(str(tmp_path / d / "001.png")) for d in ("guidance", "guidance_1"))
    assert first.shape == second.shape == (TINY.image, TINY.image, 3) and np.abs(first.astype(int) - second).mean() > 5
    assert json.loads((tmp_path / "case.json").read_text())["views"] == 2
    opt = Optimization(load_config(tmp_path / "config.yaml"))
    assert len(opt.problem.views) == 2


def test_a_case_without_room_for_its_motion_fails(tmp_path):
    # a runny fluid dropped into a domain with no room to spread reaches the walls
    case = SyntheticCase(
        shape="cube",
        lift=0.05,
        spread=0.0,
        material="newtonian",
        truth={"viscosity": 0.01, "bulk_modulus": 1e5},
        guess={},
        optimize=("viscosity",),
    )
    with pytest.raises(ValueError, match="more room"):
        make_case(tmp_path, case, dataclasses.replace(TINY, frames=10), truth_scale=1)


def test_a_truth_obeys_its_cfl_limit(tmp_path):
    # a soft block dropped 0.4 m: its wave speed asks for few substeps, its fall for more
    case = SyntheticCase(lift=0.4, spread=1.0, truth={"youngs_modulus": 2e3, "poissons_ratio": 0.3})
    with warnings.catch_warnings():
        warnings.simplefilter("error", StabilityWarning)  # no frame of the truth breaks the limit
        make_case(tmp_path, case, dataclasses.replace(TINY, frames=9), truth_scale=1)
    from clflow.pipeline.forward import prepare, scene_values
    from clflow.pipeline.simulation import build_simulator
    from clflow.scene.config import load_config

    cfg = load_config(tmp_path / "config_truth.yaml")
    at_rest = build_simulator(cfg, prepare(cfg).setup, scene_values(cfg)).substeps
    assert json.loads((tmp_path / "case.json").read_text())["truth_substeps"] >= 2 * at_rest  # run again


def test_unknown_case_is_one_clear_line(tmp_path):
    result = CliRunner().invoke(cli, ["eval", "sysid", "-o", str(tmp_path / "out"), "--case", "teapot"])
    assert result.exit_code != 0
    assert "unknown case(s) teapot" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "out").exists()


def test_a_case_out_of_range_is_refused_before_any_work(tmp_path, monkeypatch):
    bad = dataclasses.replace(CASES["torus"], guess={"poissons_ratio": 0.7})
    monkeypatch.setitem(CASES, "torus", bad)
    with pytest.raises(InputError, match="torus.*guess is out of range"):
        sysid.evaluate(["torus"], tmp_path / "out", sysid.Settings(resolution=TINY))
    assert not (tmp_path / "out").exists()


def test_a_folder_with_other_files_is_refused_without_force(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="holds other files"):
        sysid.evaluate(["torus"], out, sysid.Settings(resolution=TINY))
    assert (out / "notes.txt").read_text() == "mine"


@pytest.fixture
def tiny_cases(monkeypatch):
    """The torus case, shrunk to a few seconds."""
    case = dataclasses.replace(
        CASES["torus"], guess={"youngs_modulus": 3e5}, optimize=("youngs_modulus",), search=3, starts=1, refine=0
    )
    monkeypatch.setitem(CASES, "torus", case)


def test_rerun_skips_finished_cases_and_other_settings_need_force(tmp_path, tiny_cases):
    out = tmp_path / "out"
    first = sysid.evaluate(["torus"], out, sysid.Settings(resolution=TINY))
    record = first["cases"]["torus"]
    assert record["status"] == "ok" and 1 <= record["iterations"] <= TINY.iterations
    assert set(record["parameters"]) == {"youngs_modulus"} and record["floor_epe_px"] >= 0
    table = (out / "sysid.md").read_text()
    assert "| torus | elastic |" in table and "PhysFlow RE/EPE" in table and "0.51/1.04" in table
    assert "| median |" in table  # beside the mean, which one unobservable parameter can swamp
    assert f"| {record['final_loss']:.3g} / {record['truth_loss']:.3g} |" in table
    rows = main_table_rows(table)
    assert len({row.count("|") for row in rows}) == 1  # every row as wide as the header
    again = sysid.evaluate(["torus"], out, sysid.Settings(resolution=TINY))
    assert again["cases"]["torus"] == record  # skipped, not rerun
    other = sysid.Settings(resolution=TINY, noise=2.0)
    with pytest.raises(InputError, match="other settings.*noise: 0.0 -> 2.0"):
        sysid.evaluate(["torus"], out, other)
    assert json.loads((out / "sysid.json").read_text())["cases"]["torus"] == record  # nothing lost
    replaced = sysid.evaluate(["torus"], out, other, force=True)
    assert replaced["settings"]["noise"] == 2.0 and replaced["cases"]["torus"]["generation"]["noise"] == 2.0


def test_a_budget_chooses_each_case_s_grid_and_the_table_names_it(tmp_path, tiny_cases):
    with pytest.raises(InputError, match=r"optimize.budget: .* is too small"):  # the first case ends the run
        sysid.evaluate(["torus"], tmp_path / "small", sysid.Settings(resolution=TINY, case_budget=0.01))
    summary = sysid.evaluate(["torus"], tmp_path / "out", sysid.Settings(resolution=TINY, case_budget=1e4))
    record = summary["cases"]["torus"]
    truth_grid = record["generation"]["truth_grid_resolution"]
    assert record["budget"]["grid"] == record["grid"]["main"] <= (truth_grid - 1) / sysid.TRUTH_MARGIN + 1
    assert record["grid"]["main"] > record["grid"]["search"]  # a generous budget refines
    table = (tmp_path / "out" / "sysid.md").read_text()
    assert f" on {record['grid']['main']} nodes |" in table and "a budget of 10000 s per case" in table


def test_the_clock_fitted_is_reported_apart_from_the_material(tmp_path, tiny_cases):
    from clflow_datasets.degradation import Degradation

    settings = sysid.Settings(resolution=TINY, degradation=Degradation(speed=0.8), fit_time_scale=True)
    record = sysid.evaluate(["torus"], tmp_path / "out", settings)["cases"]["torus"]
    assert record["status"] == "ok" and set(record["parameters"]) == {"youngs_modulus"}
    assert record["mean_re"] == record["parameters"]["youngs_modulus"]["re"]  # the material's alone
    clock = record["time_scale"]
    assert clock["truth"] == 0.8 and clock["re"] == pytest.approx(abs(clock["found"] - 0.8) / 0.8)
    assert clock["found"] != 1.0  # it moved from the video's own clock
    table = (tmp_path / "out" / "sysid.md").read_text()
    assert f"time_scale: {sysid_report._fmt(clock['found'])}" in table


def test_an_interrupted_case_resumes_its_optimisation(tmp_path, tiny_cases, monkeypatch):
    from clflow.pipeline import fit

    # Adam runs its count: the tiny torus' loss is so flat that Levenberg-Marquardt, within
    # its trust region, may stop by progress after one iteration, leaving nothing to resume
    monkeypatch.setitem(CASES, "torus", dataclasses.replace(CASES["torus"], method="adam"))
    out = tmp_path / "out"
    real_run = fit.Optimization.run

    def interrupted(self, resume=False, stop_after=None):
        real_run(self, resume=resume, stop_after=1)
        raise KeyboardInterrupt

    monkeypatch.setattr(fit.Optimization, "run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        sysid.evaluate(["torus"], out, sysid.Settings(resolution=TINY))
    checkpoint = json.loads((out / "cases" / "torus" / "results" / "checkpoint.json").read_text())
    assert checkpoint["state"]["iteration"] == 1
    monkeypatch.setattr(fit.Optimization, "run", real_run)
    resumed = sysid.evaluate(["torus"], out, sysid.Settings(resolution=TINY))["cases"]["torus"]
    assert resumed["status"] == "ok" and 1 <= resumed["iterations"] <= TINY.iterations


def test_a_changed_case_definition_is_made_and_run_again(tmp_path, tiny_cases, monkeypatch):
    out = tmp_path / "out"
    first = sysid.evaluate(["torus"], out, sysid.Settings(resolution=TINY))["cases"]["torus"]
    changed = dataclasses.replace(CASES["torus"], lift=0.25)
    monkeypatch.setitem(CASES, "torus", changed)
    second = sysid.evaluate(["torus"], out, sysid.Settings(resolution=TINY))["cases"]["torus"]
    assert first["generation"]["definition"]["lift"] != second["generation"]["definition"]["lift"] == 0.25
    assert (
        yaml.safe_load((out / "cases" / "torus" / "config.yaml").read_text())["object"]["select"]["box"]["min"][1] > 0.2
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, held, bound, unsure, ranged",
    [("torus", ("youngs_modulus",), 0.15, ("poissons_ratio",), ("youngs_modulus", "poissons_ratio")),
     ("playdoh", ("youngs_modulus", "poissons_ratio", "yield_stress"), 0.3, (), ("youngs_modulus", "poissons_ratio", "yield_stress")),
     ("droplet", ("viscosity", "bulk_modulus"), 0.2, ("bulk_modulus",), ("viscosity", "bulk_modulus"))],
)  # fmt: skip
def test_a_quick_case_reaches_the_loss_of_the_ground_truth(tmp_path, name, held, bound, unsure, ranged):
    """End to end on an honest case (`clflow eval sysid --quick --case NAME`, guidance from a
    2x finer simulation and rendering, both with FLIP 0.99): from the published guess, 1-2
    decades off, the search and its three polished starts on the base grid and the main
    phase on one 1.5x finer reach a loss within 20 % of the ground truth's own on that grid
    (each against the flow estimator's error at its own parameters; near the truth the
    quick droplet's loss varies by +-15 % between points 5 % apart), a flow error near the
    truth's, and a mean RE <= ``bound`` over the ``held`` parameters: the stricter quick
    target's 0.15 for the torus' E, the quick target's 0.3 for playdoh, 0.2 for the droplet
    (playdoh's and the droplet's losses end below their truth's: the quick model's own
    minimum; the measured figures: docs/benchmarks.md and its log). Parameters the loss
    hardly sees are held to being reported weakly constrained and grid-sensitive
    (``unsure``): the torus' nu and the droplet's bulk modulus (the grid check's shifts:
    docs/history/benchmarks-2026-11.md). Every 90 % range holds the truth (playdoh's E only
    thanks to the search samples within the loss tolerance: docs/history/benchmarks-2026-11.md,
    "Ranges that hold the truth")."""
    result = CliRunner().invoke(cli, ["eval", "sysid", "--quick", "--case", name, "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    record = json.loads((tmp_path / "out" / "sysid.json").read_text())["cases"][name]
    assert record["status"] == "ok"
    history = json.loads((tmp_path / "out" / "cases" / name / "results" / "history.json").read_text())
    assert record["final_loss"] <= 1.2 * record["truth_loss"] < history[0]["loss"]
    assert record["epe_px"] <= 1.05 * record["floor_epe_px"]
    assert record["unexplained"] < 0.02  # of the observed motion (clean guidance; a warning above 0.1)
    assert sum(record["parameters"][n]["re"] for n in held) / len(held) <= bound, record["parameters"]
    assert set(unsure) <= set(record["identifiability"]["weakly_constrained"])
    assert set(unsure) <= set(record["identifiability"]["grid_sensitive"])
    assert all(record["parameters"][n]["holds_truth"] for n in ranged), record["parameters"]


@pytest.mark.slow
def test_parallel_cases_on_ray_give_the_serial_results(tmp_path, tiny_cases, monkeypatch):
    pytest.importorskip("ray")
    from clflow.sweep import sysid_on_ray

    bird = dataclasses.replace(
        CASES["bird"], guess={"youngs_modulus": 1e5}, optimize=("youngs_modulus",), search=3, starts=1, refine=0
    )
    monkeypatch.setitem(CASES, "bird", bird)  # the tasks get the driver's definitions
    settings = sysid.Settings(resolution=TINY)
    serial = sysid.evaluate(["torus", "bird"], tmp_path / "serial", settings)
    parallel = sysid.evaluate(["torus", "bird"], tmp_path / "parallel", settings, run_cases=sysid_on_ray())
    timing = {"seconds", "optimise_seconds", "generation_seconds", "generation"}  # generation: times, paths
    assert list(parallel["cases"]) == ["torus", "bird"]
    for name, record in serial["cases"].items():
        assert record["status"] == "ok"
        same = {k: v for k, v in record.items() if k not in timing}
        assert {k: v for k, v in parallel["cases"][name].items() if k not in timing} == same, name


def test_the_table_says_what_the_check_found_of_each_parameter():
    record = {
        "identifiability": {
            "weakly_constrained": ["bulk_modulus", "viscosity"],
            "unresolved": ["viscosity"],
            "profile": {"bulk_modulus": {"values": [1e4, 1e6]}, "viscosity": {"values": [18.8, 0.188]}},
            "grids": [51, 76],
            "grid_shift_z": {"bulk_modulus": -0.05, "viscosity": 0.2, "yield_stress": -0.42},
            "grid_sensitive": ["yield_stress"],
        }
    }
    assert sysid_report._caveat("viscosity", record) == " (loss flat from 0.188 to 18.8)"
    assert sysid_report._caveat("bulk_modulus", record) == " (weakly constrained)"
    assert sysid_report._caveat("yield_stress", record) == " (grid-sensitive, -0.42 on 51 nodes)"
    assert sysid_report._caveat("shear_modulus", record) == ""


def test_the_table_says_what_the_prior_decided_and_the_video_s_own_mean():
    nu = {"found": 0.3, "truth": 0.3, "re": 0.0, "decided_by": "prior", "video_fit": 0.06, "video_re": 0.8}
    e = {"found": 2e6, "truth": 2e6, "re": 0.1, "decided_by": "video", "video_fit": 2.2e6, "video_re": 0.1}
    record = {"identifiability": {"weakly_constrained": ["poissons_ratio"]}, "parameters": {"poissons_ratio": nu}}
    assert sysid_report._caveat("poissons_ratio", record) == (
        " (weakly constrained; prior: the video's own 0.06, RE 0.800)"
    )
    case = {"status": "ok", "mean_re": 0.05, "epe_px": 0.2, "parameters": {"poissons_ratio": nu, "youngs_modulus": e}}
    (row,) = sysid_report._video_alone_row([case], ())
    assert "it decided 1 parameters" in row and "| 0.450 |" in row
    assert sysid_report._video_alone_row([{**case, "parameters": {"youngs_modulus": {"re": 0.1}}}], ()) == []


def test_the_benchmark_searches_on_the_base_grid_and_refines_on_a_finer_one(tmp_path):
    case = dataclasses.replace(CASES["torus"])
    config = make_case(tmp_path, case, dataclasses.replace(TINY, main_grid_scale=1.5, flip=0.99), truth_scale=2)
    truth, opt = (yaml.safe_load((tmp_path / name).read_text()) for name in ("config_truth.yaml", "config.yaml"))
    # truth and optimiser alike blend FLIP in, as the benchmark's resolutions ask
    assert sysid.FULL.flip == sysid.QUICK.flip == truth["simulation"]["flip"] == opt["simulation"]["flip"] == 0.99
    base = (truth["simulation"]["grid_resolution"] - 1) // 2 + 1
    assert opt["optimize"]["search"]["grid_resolution"] == base
    assert opt["simulation"]["grid_resolution"] == round((base - 1) * 1.5) + 1 < truth["simulation"]["grid_resolution"]
    from clflow.pipeline.fit import Optimization
    from clflow.scene.config import load_config

    optimization = Optimization(load_config(config))
    assert optimization.cfg.simulation.flip == 0.99
    (coarse, fine) = (optimization.problem._prepared[n].setup for n in (base, opt["simulation"]["grid_resolution"]))
    assert coarse.grid.dx == pytest.approx(1.5 * fine.grid.dx, rel=0.05)
    assert coarse.particles.positions.shape[0] < fine.particles.positions.shape[0]  # each grid its own fill
    n = optimization.problem.prepared.obj_rest.means.shape[0]  # the Gaussians come first in either: one render
    assert torch.equal(coarse.particles.positions[:n], fine.particles.positions[:n])


@pytest.mark.slow
def test_the_loss_scan_gives_the_loss_and_both_gradients_along_a_parameter(tmp_path, tiny_cases):
    """experiments/loss_scan.py on a finished case: per value the loss at the final point's
    calibration, the adjoint's dloss/dz and the optimiser's backward difference, which agree
    where the loss is smooth, and the loss against the estimator's error at the value itself;
    with --grid the same on another grid over the same domain."""
    import subprocess
    import sys

    from tests.conftest import REPO

    landing = dataclasses.replace(TINY, frames=10)  # the torus lands at frame 6: E shows
    sysid.evaluate(["torus"], tmp_path / "out", sysid.Settings(resolution=landing))
    config, scan = tmp_path / "out" / "cases" / "torus" / "config.yaml", tmp_path / "scan.json"
    cmd = [sys.executable, "experiments/loss_scan.py", str(config), "youngs_modulus", "1e4", "3e5", "--points", "3"]
    res = subprocess.run([*cmd, "--json", str(scan)], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = json.loads(scan.read_text())["rows"]
    assert [r["value"] for r in rows] == [1e4, 1.55e5, 3e5]
    assert rows[0]["loss"] > rows[1]["loss"] > rows[2]["loss"] > 0  # towards the truth, 1e6
    for row in rows:
        assert row["self_consistent_loss"] > 0 and row["adjoint_dz"] < 0
        assert abs(row["adjoint_dz"] - row["lm_backward_difference_dz"]) < 0.1 * abs(row["adjoint_dz"])
    assert "scan_central_difference_dz" in rows[1]
    # --grid: the same scan on a finer grid over the same domain, at that grid's own substeps
    finer = rows[0]["grid"] + 6
    res = subprocess.run(
        [*cmd, "--grid", str(finer), "--json", str(scan)], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stderr[-3000:]
    on_finer = json.loads(scan.read_text())["rows"]
    assert {r["grid"] for r in on_finer} == {finer}
    assert on_finer[0]["loss"] > on_finer[1]["loss"] > on_finer[2]["loss"] > 0
    assert [r["loss"] for r in on_finer] != [r["loss"] for r in rows]


def test_case_variant_losses_scores_a_case_made_with_other_truth_values(tmp_path, tiny_cases):
    """experiments/case_variant_losses.py: a case made with a truth value changed scores lowest
    near that value; the folder remembers how it was made and refuses another making; a
    name outside the case's truth is refused."""
    import importlib.util

    from tests.conftest import REPO

    spec = importlib.util.spec_from_file_location(
        "case_variant_losses", Path(REPO) / "experiments" / "case_variant_losses.py"
    )
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    landing = dataclasses.replace(TINY, frames=10)  # the torus lands at frame 6: E shows
    values = [1e4, 1e5, 1e6]
    losses = {}
    for truth in (1e6, 1e4):
        out = tmp_path / f"truth_{truth:g}"
        case = script.make_variant("torus", out, landing, {"youngs_modulus": truth}, truth_scale=2)
        assert (
            yaml.safe_load((out / "config_truth.yaml").read_text())["material"]["parameters"]["youngs_modulus"] == truth
        )
        rows = script.losses_along(out / "config.yaml", case.truth, "youngs_modulus", values)
        assert [r["value"] for r in rows] == values and all(r["loss"] > 0 for r in rows)
        losses[truth] = [r["loss"] for r in rows]
    assert losses[1e6][0] > losses[1e6][1] > losses[1e6][2]  # towards each truth
    assert losses[1e4][0] < losses[1e4][1] < losses[1e4][2]
    with pytest.raises(SystemExit, match="made otherwise"):
        script.make_variant("torus", tmp_path / "truth_1e+06", landing, {"youngs_modulus": 2e6}, truth_scale=2)
    with pytest.raises(SystemExit, match="not among torus's truth values"):
        script.make_variant("torus", tmp_path / "other", landing, {"friction_angle": 30.0}, truth_scale=2)
    assert not (tmp_path / "other").exists()
