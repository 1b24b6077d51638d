"""``clflow query``, driven through click's test runner."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from clflow.query import BACKENDS, load_query_result
from clflow_cli.main import cli
from clflow_cli.query import BACKEND_CHOICES

from .conftest import API_KEY, chat


@pytest.fixture
def run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)

    def invoke(*args: str):
        return CliRunner().invoke(cli, ["query", *map(str, args)], catch_exceptions=False)

    return invoke


# a model's answer for a jar of honey, in units it has to convert (g/cm^3)
HONEY = {
    "object": "jar of honey",
    "material": "newtonian",
    "density": {"value": 1.42, "unit": "g/cm^3"},
    "parameters": {"viscosity": {"value": 8, "unit": "Pa*s"}, "bulk_modulus": {"value": 1e5, "unit": "Pa"}},
    "confidence": 0.7,
}


def test_backend_choices_match_the_library():
    assert BACKEND_CHOICES == BACKENDS
    assert "query" in CliRunner().invoke(cli, ["--help"]).output


def test_offline_summary_and_default_output(run, photo, tmp_path):
    res = run(photo[0], "--box", "0,0,32,24")
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0].startswith("object      rubber duck  (knowledge-base entry 'rubber', confidence 0.70)")
    assert "material    elastic: fixed corotated" in res.output
    assert "density     1100 kg/m^3" in res.output
    assert "parameters  youngs_modulus (E)   5e+06 Pa" in res.output
    assert lines[-1] == "wrote rubber_duck.material.json"
    loaded = load_query_result(tmp_path / "rubber_duck.material.json")
    assert loaded.crop_box == [0, 0, 32, 24] and loaded.backend == "offline"


def test_json_output_and_warnings(run, photo, tmp_path):
    image = photo[0].rename(tmp_path / "IMG_0001.png")  # a file name that names nothing
    res = run(image, "--name", "xyzzy newtonian", "--json", "-o", tmp_path / "q" / "x.json")  # a type, no entry
    assert res.exit_code == 0
    printed = json.loads(res.output)
    assert printed == json.loads((tmp_path / "q" / "x.json").read_text())
    assert printed["matched"] is None and printed["material"] == "newtonian" and printed["warnings"]
    res = run(image, "--name", "xyzzy newtonian")
    assert "warning: no knowledge-base entry matches 'xyzzy newtonian" in res.output


def test_an_answer_the_offline_backend_cannot_give_is_refused_and_nothing_written(run, photo, tmp_path):
    """No --name, a file name that names nothing: the knowledge base's default entry ('rubber')
    is no answer; it used to be written into the current folder with exit 0."""
    image = photo[0].rename(tmp_path / "000.png")
    res = run(image, "-o", tmp_path / "q.json")
    assert res.exit_code == 1 and "cannot tell what 000.png shows" in res.output and "--name" in res.output
    assert not (tmp_path / "q.json").exists()


def test_openai_backend_from_options_and_environment(run, photo, server, monkeypatch, tmp_path):
    monkeypatch.setenv("CLFLOW_LLM_API_KEY", API_KEY)
    server.play(chat({**HONEY, "reasoning": "golden, viscous"}))
    res = run(
        photo[0],
        "--backend",
        "openai",
        "--llm-url",
        server.base_url,
        "--model",
        "llava",
        "--prompt",
        "honey dripping",
        "--image-format",
        "jpeg",
    )
    assert res.exit_code == 0, res.output
    assert "material    newtonian" in res.output and "viscosity (mu)        8 Pa*s" in res.output
    assert "backend     openai (model llava, json_schema)" in res.output
    assert "warning: density: converted 1.42 g/cm^3 to 1420 kg/m^3" in res.output
    assert server.requests[0].headers["Authorization"] == f"Bearer {API_KEY}"
    assert "honey dripping" in server.requests[0].body["messages"][1]["content"][0]["text"]
    saved = (tmp_path / "rubber_duck.material.json").read_text()
    assert API_KEY not in saved and API_KEY not in res.output
    assert load_query_result(tmp_path / "rubber_duck.material.json").model == "llava"


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing.png"], "Error: image missing.png does not exist"),
        (["{img}", "--box", "0,0,100,10"], "Error: box (0, 0, 100, 10) is outside the 64x48 px image"),
        (["{img}", "--mask", "nomask.png"], "Error: mask nomask.png does not exist"),
        (["{img}", "--backend", "openai"], "Error: the openai backend needs an endpoint"),
        (
            ["{img}", "--backend", "openai", "--llm-url", "https://api.example.com/v1", "--model", "m"],
            "Error: no API key for api.example.com",
        ),
        (
            ["{img}", "--backend", "openai", "--llm-url", "{refused}", "--model", "m", "--retries", "0"],
            "Error: model server http://127.0.0.1:",
        ),
    ],
)
def test_errors_are_one_line(run, photo, refused_url, args, message):
    args = [a.format(img=photo[0], refused=refused_url) for a in args]
    res = run(*args)
    assert res.exit_code == 1
    assert res.output.strip().splitlines()[-1].startswith(message) and "Traceback" not in res.output


def test_box_is_one_word_with_commas_and_the_old_spaced_form_says_so(run, photo):
    res = run(photo[0], "--box", 0, 0, 32, 24)  # the spelling before cli/options.py
    assert res.exit_code == 2 and "write them as one word with commas, e.g. X0,Y0,X1,Y1" in res.output
    assert run(photo[0], "--box", "0 0 32 24", "--json").exit_code == 0  # quoted, spaces are read too


def test_unknown_backend_is_a_usage_error(run, photo):
    res = run(photo[0], "--backend", "gpt4")
    assert res.exit_code == 2 and "'gpt4' is not one of 'offline', 'openai'" in res.output


def test_benchmark_runs():
    res = CliRunner().invoke(cli, ["bench", "query", "--repeat", "1"], catch_exceptions=False)
    assert res.exit_code == 0
    assert res.output.startswith("offline lookup first") and "image jpeg encode" in res.output


def test_each_warning_of_a_model_answer_is_shown_once(photo, server, tmp_path):
    """The unit conversion was logged by the query and printed again in the summary."""
    import subprocess
    import sys

    server.play(chat(HONEY))
    res = subprocess.run(
        [sys.executable, "-m", "clflow_cli", "query", str(photo[0]), "--backend", "openai",
         "--llm-url", server.base_url, "--model", "llava", "-o", str(tmp_path / "q.json")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert (res.stdout + res.stderr).count("converted 1.42 g/cm^3 to 1420 kg/m^3") == 1, res.stdout + res.stderr
