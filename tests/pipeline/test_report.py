"""The results page: index.html and run.json of `clflow optimize`, opened in a headless browser."""

import html
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from click.testing import CliRunner

from clflow_cli.main import cli

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def results(quick_demo, tmp_path_factory):
    import sys

    out = tmp_path_factory.mktemp("report") / "results"
    args = ["optimize", str(quick_demo / "config.yaml"), "--iterations", "1", "-o", str(out)]
    argv, sys.argv = sys.argv, ["clflow", *args]  # the command line run.json records
    try:
        res = CliRunner().invoke(cli, args)
    finally:
        sys.argv = argv
    assert res.exit_code == 0, res.output
    assert "open index.html" in res.output
    return out


def test_run_json_says_what_made_the_results(results):
    run = json.loads((results / "run.json").read_text())
    env = run["environment"]
    assert (
        env["torch"].startswith("2.13") and env["pyopencl"] and "Portable Computing Language" in env["opencl_platform"]
    )
    assert run["config"]["material"]["type"] == "elastic" and run["config"]["optimize"]["iterations"] == 1
    assert run["command"][:2] == ["clflow", "optimize"]


def test_the_page_links_only_files_beside_it(results):
    page = (results / "index.html").read_text()
    links = re.findall(r'(?:src|href)="([^"]+)"', page)
    assert {"loss.png", "comparison.mp4", "run.json", "params.json"} <= set(links)
    for link in links:
        assert not re.match(r"[a-z]+:|/", link), link  # relative: the folder can move
        assert (results / link).is_file(), link
    assert "youngs_modulus" in page and "Pa" in page and "relative error" in page


@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed (CI installs it)")
def test_the_page_shows_in_a_browser_and_its_videos_play(results, tmp_path):
    import cv2

    url = (results / "index.html").as_uri()
    flags = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--virtual-time-budget=8000"]
    shot = tmp_path / "page.png"
    subprocess.run([*flags, "--window-size=1000,1400", f"--screenshot={shot}", url], capture_output=True, timeout=120)
    image = cv2.imread(str(shot))
    assert image is not None and image.shape[:2] == (1400, 1000)
    assert image.std() > 20 and (image < 128).mean() > 0.01  # not a blank page: text, tables, the plot
    dom = subprocess.run([*flags, "--dump-dom", url], capture_output=True, text=True, timeout=120).stdout
    durations = [float(d) for d in re.findall(r'data-duration="([0-9.]+)"', dom)]
    frames = json.loads((results / "run.json").read_text())["config"]["simulation"]["frames"]
    assert durations and durations[0] == pytest.approx(frames / 24, abs=0.05)  # comparison.mp4 decoded: H.264 plays
    assert np.all(np.array(durations) > 0)


def test_the_page_says_which_parameters_the_video_does_not_resolve(tmp_path):
    from clflow.pipeline.report import write_report

    identifiability = {
        "weakly_constrained": ["viscosity"],
        "trade_offs": [],
        "profile": {"viscosity": {"values": [0.188, 18.8], "loss_ratio": [1.001, 1.02]}},
        "profile_rise": 0.1,
        "unresolved": ["viscosity"],
        "grids": [51, 76],
        "grid_shift_z": {"viscosity": 0.01, "bulk_modulus": -0.42},
        "grid_sensitive": ["bulk_modulus"],
    }
    (tmp_path / "metrics.json").write_text(json.dumps({"flow_loss": 0.02, "identifiability": identifiability}))
    page = write_report(tmp_path).read_text()
    assert "weakly constrained: viscosity" in page
    assert "unresolved: viscosity" in page and "loss within 10 % from 0.188 to 18.8 (SI)" in page
    assert "grid-sensitive: bulk_modulus" in page and "fit moves -0.42 (optimiser units) on 51 nodes" in page


def test_the_page_says_what_the_prior_decided_and_what_the_video_alone_said(tmp_path):
    from clflow.pipeline.report import write_report

    decided = {"value": 0.4, "decided_by": "prior", "entry": "butter", "prior_range": [0.25, 0.49], "video_fit": 0.034}
    kept = {"value": 1.5e4, "decided_by": "video", "entry": "butter", "prior_range": [50, 6e7], "video_fit": 1.5e4}
    prior = {"parameters": {"poissons_ratio": decided, "yield_stress": kept}}
    (tmp_path / "metrics.json").write_text(json.dumps({"flow_loss": 0.02, "prior": prior}))
    page = write_report(tmp_path).read_text()
    assert "decided by the prior: poissons_ratio" in page and "yield_stress" not in page
    assert "0.4 (prior; butter, 0.25 - 0.49); the video alone 0.034" in page


def test_the_page_says_how_much_motion_the_fit_leaves_unexplained_and_its_warnings(tmp_path):
    from clflow.pipeline.fit.results import unexplained_warning
    from clflow.pipeline.report import write_report

    line = unexplained_warning(0.21)
    motion = {"residual_px2": 0.05, "still_px2": 0.24, "fraction": 0.21}
    (tmp_path / "metrics.json").write_text(
        json.dumps({"flow_loss": 0.05, "unexplained_motion": motion, "warnings": [line]})
    )
    page = write_report(tmp_path).read_text()
    assert "observed motion left unexplained</td><td>21.0%" in page.replace("\n", "")
    assert html.escape(line) in page


def test_the_page_gives_each_optimised_parameter_its_range(tmp_path):
    from clflow.pipeline.report import write_report

    params = {
        "material": "newtonian",
        "optimized": {"viscosity": 107.6, "bulk_modulus": 5.3e5},
        "units": {"viscosity": "Pa s", "bulk_modulus": "Pa"},
        "ranges": {
            "viscosity": {"low": 71.5, "high": 162.0, "level": 0.9},
            "bulk_modulus": {"low": 2.1e5, "high": None, "level": 0.9},
        },
        "parameters": {},
        "density": 1000.0,
        "velocity": [0, 0, 0],
    }
    (tmp_path / "params.json").write_text(json.dumps(params))
    page = write_report(tmp_path).read_text()
    assert "<th>90 % range</th>" in page
    assert "<td>71.5 - 162</td>" in page and "<td>&gt;= 2.1e+05</td>" in page


def test_the_results_hold_each_range_in_params_json_and_draw_it(results):
    params = json.loads((results / "params.json").read_text())
    ranges = json.loads((results / "metrics.json").read_text())["identifiability"]["ranges"]
    assert set(params["ranges"]) == set(params["optimized"]) == set(ranges)
    for name, value in params["optimized"].items():
        low, high = params["ranges"][name]["low"], params["ranges"][name]["high"]
        assert (low is None or low < value) and (high is None or value < high)
        assert ranges[name]["sigma_z"] >= ranges[name]["frames_z"] >= 0


def test_the_page_is_titled_by_the_scene_folder_and_its_results_folder(tmp_path):
    from clflow.pipeline.report import write_report

    results = tmp_path / "jelly" / "results"  # a scene's default output folder
    results.mkdir(parents=True)
    (results / "metrics.json").write_text(json.dumps({"flow_loss": 0.02}))
    page = write_report(results).read_text()
    assert "<title>clflow results: jelly/results</title>" in page
    assert "<h1>clflow results: jelly/results</h1>" in page
