"""The foundation-model backend against a real chat-completions server on loopback."""

from __future__ import annotations

import base64
import json
import logging
import time

import numpy as np
import pytest

from clflow.errors import InputError
from clflow.materials import MATERIALS
from clflow.query import (
    ModelAnswerError,
    ModelConfig,
    ModelServiceError,
    crop_object,
    load_knowledge_base,
    load_query_result,
    query_material,
)
from clflow.query.answer import extract_json_object
from clflow.query.llm import answer_schema, chat_endpoint, redact_url

from .conftest import API_KEY, Reply, chat, error

BOX = (8, 4, 40, 36)


def answer(**changes) -> dict:
    """A well-formed answer for a rubber duck; ``changes`` replace or (value None) drop keys."""
    a = {
        "object": "rubber duck",
        "material": "elastic",
        "density": {"value": 1100, "unit": "kg/m^3"},
        "parameters": {
            "youngs_modulus": {"value": 3e6, "unit": "Pa"},
            "poissons_ratio": {"value": 0.45, "unit": "1"},
        },
        "confidence": 0.8,
        "reasoning": "A bath toy made of soft rubber.",
    }
    a.update(changes)
    return {k: v for k, v in a.items() if v is not None}


def config(url: str, **options) -> ModelConfig:
    options = {"timeout": 2.0, "retries": 2, "backoff": 0.001, **options}
    return ModelConfig(url=chat_endpoint(url), model="test-vision", api_key=API_KEY, **options)


def ask(server, photo, **options):
    return query_material(photo[0], box=BOX, backend="openai", model_config=config(server.base_url, **options))


def test_request_carries_image_schema_and_headers(server, photo):
    server.play(chat(answer()))
    result = ask(server, photo, image_format="png")

    (req,) = server.requests
    assert req.path == "/v1/chat/completions"
    assert req.headers["Authorization"] == f"Bearer {API_KEY}"
    assert req.headers["Content-Type"] == "application/json"
    body = req.body
    assert body["model"] == "test-vision"
    system, user = body["messages"]
    assert system["role"] == "system" and user["role"] == "user"
    text = next(p["text"] for p in user["content"] if p["type"] == "text")
    for name, mat in MATERIALS.items():  # every type, parameter and unit is in the question
        assert name in text
        assert all(f"{p.name} ({p.symbol}) [{p.unit}]" in text for p in mat.params)
    url = next(p["image_url"]["url"] for p in user["content"] if p["type"] == "image_url")
    prefix = "data:image/png;base64,"
    assert url.startswith(prefix)
    import cv2

    sent = cv2.imdecode(np.frombuffer(base64.b64decode(url[len(prefix) :]), np.uint8), cv2.IMREAD_COLOR)
    x0, y0, x1, y1 = BOX
    np.testing.assert_array_equal(sent, photo[1][y0:y1, x0:x1])  # the crop, losslessly

    rf = body["response_format"]
    assert rf["type"] == "json_schema" and rf["json_schema"]["strict"] is True
    schema = rf["json_schema"]["schema"]
    assert schema == answer_schema()
    assert schema["properties"]["material"]["enum"] == list(MATERIALS)
    variants = schema["properties"]["parameters"]["anyOf"]
    assert [sorted(v["required"]) for v in variants] == [sorted(m.param_names) for m in MATERIALS.values()]
    units = {n: q["properties"]["unit"]["enum"] for v in variants for n, q in v["properties"].items()}
    assert units["youngs_modulus"] == ["Pa"] and units["viscosity"] == ["Pa*s"]

    assert result.material == "elastic" and result.density == 1100.0
    assert result.parameters == {"youngs_modulus": 3e6, "poissons_ratio": 0.45}
    assert result.backend == "openai" and result.model == "test-vision"
    assert result.object == "rubber duck" and result.confidence == 0.8
    assert result.prompt == text
    assert json.loads(result.raw_answer) == answer()
    assert result.crop_box == list(BOX) and result.structured_output is True
    assert result.matched == "rubber"  # the object the model named, in the knowledge base
    assert result.warnings == []


def test_a_type_that_contradicts_the_knowledge_base_is_flagged(server, photo):
    server.play(chat(answer(object="honey jar", material="elastic")))
    result = ask(server, photo)
    assert result.material == "elastic" and result.matched == "honey"
    assert result.warnings == [
        "the model chose elastic for 'honey jar'; the knowledge base files 'honey' under newtonian"
    ]


def test_jpeg_images_are_sent_as_jpeg(server, photo):
    server.play(chat(answer()))
    ask(server, photo, image_format="jpeg")
    (req,) = server.requests
    url = req.body["messages"][1]["content"][1]["image_url"]["url"]
    assert url.startswith("data:image/jpeg;base64,/9j/")  # JPEG's SOI marker, base64


def test_mask_crops_to_the_mask_and_whitens_the_rest(tmp_path, photo):
    import cv2

    mask = np.zeros(photo[1].shape[:2], np.uint8)
    mask[10:20, 30:35] = 255
    mask[12, 29] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    crop = crop_object(photo[0], mask_path=tmp_path / "mask.png")
    assert crop.box == (29, 10, 35, 20)
    expected = np.where(mask[10:20, 29:35, None] > 0, photo[1][10:20, 29:35], 255)
    np.testing.assert_array_equal(crop.pixels, expected)


def test_api_key_is_never_logged_saved_or_shown(server, photo, tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    server.play(error(503, "busy"), chat(answer()))
    result = ask(server, photo)
    out = result.save(tmp_path / "r.json")
    # a server that echoes the key in its error message
    server.play(error(401, f"Incorrect API key provided: {API_KEY}"))
    with pytest.raises(ModelServiceError) as exc:
        ask(server, photo)
    cfg = config(server.base_url)
    assert API_KEY not in out.read_text()
    assert API_KEY not in caplog.text and "retrying" in caplog.text
    assert API_KEY not in str(exc.value) and "***" in str(exc.value)
    assert API_KEY not in repr(cfg) and API_KEY not in str(cfg)


def test_key_and_endpoint_come_from_the_environment(monkeypatch, server):
    monkeypatch.setenv("CLFLOW_LLM_URL", server.base_url + "/")
    monkeypatch.setenv("CLFLOW_LLM_MODEL", "llava")
    monkeypatch.setenv("OPENAI_API_KEY", "sk-fallback")
    cfg = ModelConfig.resolve()
    assert (cfg.url, cfg.model, cfg.api_key) == (server.base_url + "/chat/completions", "llava", "sk-fallback")
    monkeypatch.setenv("CLFLOW_LLM_API_KEY", "sk-first")
    assert ModelConfig.resolve(model="other").api_key == "sk-first"
    assert ModelConfig.resolve("https://api.example.com/v1/chat/completions", "m").url == (
        "https://api.example.com/v1/chat/completions"
    )


def test_loopback_server_needs_no_key(server, photo):
    server.play(chat(answer()))
    cfg = ModelConfig.resolve(server.base_url, "llava", backoff=0.001)
    assert cfg.api_key is None
    query_material(photo[0], backend="openai", model_config=cfg)
    assert "Authorization" not in server.requests[0].headers


def test_bad_settings():
    with pytest.raises(InputError, match="timeout > 0 s"):
        ModelConfig("http://localhost/v1/chat/completions", "m", timeout=0)
    with pytest.raises(InputError, match="'gif' is not 'png' or 'jpeg'"):
        ModelConfig.resolve("http://localhost/v1", "m", image_format="gif")


@pytest.mark.parametrize(
    "url, model, key, message",
    [
        (None, "m", "k", "needs an endpoint"),
        ("http://localhost:11434/v1", None, "k", "needs a model name"),
        ("https://api.example.com/v1", "m", None, "no API key for api.example.com"),
        ("ftp://example.com/v1", "m", "k", r"not an http\(s\) URL"),
        ("localhost:11434", "m", "k", r"not an http\(s\) URL"),
    ],
)
def test_missing_or_bad_endpoint_model_or_key(monkeypatch, url, model, key, message):
    if key:
        monkeypatch.setenv("CLFLOW_LLM_API_KEY", key)
    with pytest.raises(InputError, match=message):
        ModelConfig.resolve(url, model)


@pytest.mark.parametrize(
    "content, warned",
    [
        (json.dumps(answer()), False),
        ("  \n" + json.dumps(answer()) + "\n", False),
        ("Here is my answer:\n```json\n" + json.dumps(answer(), indent=1) + "\n```\nHope it helps {sic", True),
    ],
)
def test_json_is_extracted_by_the_stated_rule(server, photo, content, warned):
    server.play(chat(content))
    result = ask(server, photo)
    assert result.parameters["youngs_modulus"] == 3e6
    assert ("text around the JSON answer was ignored" in result.warnings) == warned


@pytest.mark.parametrize(
    "content, message",
    [
        ("I think it is rubber.", "no JSON object"),
        ('{"material": "elastic", "density": ', "no JSON object"),
        ('{"material": "elastic"} or maybe {"material": "foam"}', "2 JSON objects"),
        ('["elastic"]', "not an object"),
        ('{"material": "elastic", "density": NaN}', "no JSON object"),
        ("", "empty"),
    ],
)
def test_malformed_answers_are_rejected(server, photo, content, message):
    server.play(chat(content))
    with pytest.raises(ModelAnswerError, match=message):
        ask(server, photo)


def test_missing_material_is_rejected_missing_numbers_take_defaults(server, photo):
    server.play(chat(answer(material=None)))
    with pytest.raises(ModelAnswerError, match="no material type"):
        ask(server, photo)

    only_e = {"youngs_modulus": {"value": 7e10, "unit": "Pa"}}
    server.play(chat(answer(material="metal", density=None, parameters=only_e)))
    result = ask(server, photo)
    steel = load_knowledge_base().default_entry("metal")  # the documented default of metal
    assert result.material == "metal"
    assert result.density == steel.density.value
    assert result.parameters == {**steel.parameter_values(), "youngs_modulus": 7e10}
    missing = [w for w in result.warnings if "is missing" in w]
    assert len(missing) == 4  # density, nu, tau_Y, xi

    server.play(chat(answer(parameters=None)))
    result = ask(server, photo)
    assert any("no parameters object" in w for w in result.warnings)


def test_unknown_material_types(server, photo):
    server.play(chat(answer(material="unobtainium")))
    with pytest.raises(ModelAnswerError, match="unknown material type 'unobtainium'.*elastic"):
        ask(server, photo)
    server.play(chat(answer(material="Jelly")))  # a registry alias: no warning
    result = ask(server, photo)
    assert result.material == "elastic" and result.warnings == []
    server.play(chat(answer(material="steel", parameters={})))  # an object, filed in the knowledge base
    result = ask(server, photo)
    assert result.material == "metal" and "'steel' under metal" in result.warnings[0]


def test_invalid_values_take_defaults_atypical_values_are_clamped(server, photo):
    rubber = load_knowledge_base().default_entry("elastic")
    server.play(
        chat(
            answer(
                density={"value": 0.001, "unit": "kg/m^3"},
                parameters={
                    "youngs_modulus": {"value": -5e6, "unit": "Pa"},
                    "poissons_ratio": {"value": 0.7, "unit": "1"},
                },
            )
        )
    )
    result = ask(server, photo)
    assert result.density == 10.0  # registry's typical minimum
    assert result.parameters == rubber.parameter_values()
    assert any("clamped to 10" in w for w in result.warnings)
    assert any("youngs_modulus (E) = -5e+06 Pa is outside the valid range" in w for w in result.warnings)
    assert any("poissons_ratio (nu) = 0.7" in w for w in result.warnings)

    server.play(
        chat(
            answer(
                parameters={
                    "youngs_modulus": {"value": 1e13, "unit": "Pa"},
                    "poissons_ratio": {"value": "0.3", "unit": "1"},
                    "shear_modulus": {"value": 1.0, "unit": "Pa"},
                },
                confidence=85,
            )
        )
    )
    result = ask(server, photo)
    assert result.parameters["youngs_modulus"] == 2e11
    assert result.parameters["poissons_ratio"] == rubber.parameters["poissons_ratio"].value
    assert result.confidence is None
    text = "\n".join(result.warnings)
    for fragment in ("clamped to 2e+11", "'0.3' is not a number", "ignored parameter 'shear_modulus'", "confidence 85"):
        assert fragment in text


def test_units_are_converted_or_refused(server, photo):
    server.play(
        chat(
            answer(
                material="sand",
                density={"value": 1.6, "unit": "g/cm³"},
                parameters={
                    "phi": {"value": 0.6, "unit": "rad"},
                    "cohesion": {"value": 0, "unit": ""},
                    "youngs_modulus": {"value": 0.35, "unit": "MPa"},
                    "poissons_ratio": 0.3,
                },
            )
        )
    )
    result = ask(server, photo)
    assert result.density == pytest.approx(1600.0)
    assert result.parameters["friction_angle"] == pytest.approx(np.degrees(0.6))
    assert result.parameters["youngs_modulus"] == pytest.approx(3.5e5)
    assert result.parameters["poissons_ratio"] == 0.3
    text = "\n".join(result.warnings)
    assert "converted 1.6 g/cm³ to 1600 kg/m^3" in text and "converted 0.35 MPa" in text
    assert "poissons_ratio has no unit" in text

    server.play(
        chat(
            answer(
                material="newtonian",
                parameters={
                    "viscosity": {"value": 1, "unit": "cP"},
                    "bulk_modulus": {"value": 2.2, "unit": "furlongs"},
                },
            )
        )
    )
    result = ask(server, photo)
    water = load_knowledge_base().default_entry("newtonian")
    assert result.parameters == {
        "viscosity": pytest.approx(1e-3),
        "bulk_modulus": water.parameters["bulk_modulus"].value,
    }
    assert any("unit 'furlongs' is not a unit of Pa" in w for w in result.warnings)


def test_client_errors_are_not_retried(server, photo):
    server.play(error(401, "Invalid authentication"))
    refused = r"refused the request: HTTP 401 .*Invalid authentication \(check the API key\)"
    with pytest.raises(ModelServiceError, match=refused):
        ask(server, photo)
    assert len(server.requests) == 1
    server.play(error(404, "model 'test-vision' not found"))
    with pytest.raises(ModelServiceError, match=r"HTTP 404.*not found \(check --llm-url and --model\)"):
        ask(server, photo)


def test_server_errors_are_retried_with_backoff(server, photo, monkeypatch):
    delays = []
    monkeypatch.setattr("clflow.query.llm.time.sleep", delays.append)
    server.play(error(500, "internal error"))
    with pytest.raises(ModelServiceError, match="after 4 attempts: HTTP 500 .*internal error"):
        ask(server, photo, retries=3, backoff=0.5, max_backoff=1.5)
    assert len(server.requests) == 4
    assert delays == [0.5, 1.0, 1.5]  # doubling, capped

    delays.clear()
    server.requests.clear()
    server.play(error(429, "slow down", Retry_After="0.25"), error(503, "overloaded"), chat(answer()))
    result = ask(server, photo, retries=2, backoff=0.01)
    assert result.material == "elastic" and len(server.requests) == 3
    assert delays == [0.25, 0.02]  # the server's Retry-After, then the backoff


def test_slow_server_times_out(server, photo):
    server.play(Reply(200, {}, delay=5.0))
    start = time.monotonic()
    with pytest.raises(ModelServiceError, match=r"after 2 attempts: no answer within the 0.2 s timeout"):
        ask(server, photo, timeout=0.2, retries=1)
    assert time.monotonic() - start < 2.0
    assert len(server.requests) == 2


def test_connection_refused(refused_url, photo):
    cfg = config(refused_url, retries=1)
    with pytest.raises(ModelServiceError, match=r"could not be reached after 2 attempts: connection refused"):
        query_material(photo[0], backend="openai", model_config=cfg)


def test_server_without_json_schema_gets_a_plain_prompt(server, photo, tmp_path):
    server.play(
        error(400, "response_format json_schema is not supported"),
        chat("Sure! " + json.dumps(answer()) + " Let me know."),
    )
    result = ask(server, photo)
    first, second = (r.body for r in server.requests)
    assert "response_format" in first and "response_format" not in second
    assert first["messages"] == second["messages"]
    assert result.structured_output is False and result.parameters["youngs_modulus"] == 3e6
    assert any("rejected the json_schema response format" in w for w in result.warnings)
    assert load_query_result(result.save(tmp_path / "r.json")).structured_output is False


@pytest.mark.parametrize(
    "reply, error_type, message",
    [
        (Reply(200, b"<html>gateway</html>"), ModelServiceError, "did not answer as a chat-completions server"),
        (Reply(200, {"choices": []}), ModelServiceError, "did not answer as a chat-completions server"),
        (Reply(200, {"choices": [{"message": "hi"}]}), ModelServiceError, "did not answer as a chat-completions"),
        (chat("", refusal="I can't help with that."), ModelAnswerError, "refused to answer: I can't"),
        (chat("", finish_reason="length"), ModelAnswerError, "empty.*length"),
    ],
)
def test_protocol_violations(server, photo, reply, error_type, message):
    server.play(reply)
    with pytest.raises(error_type, match=message):
        ask(server, photo)


def test_content_parts_are_joined(server, photo):
    text = json.dumps(answer())
    server.play(
        Reply(
            200,
            {
                "choices": [
                    {
                        "message": {
                            "role": "assistant",
                            "content": [{"type": "text", "text": text[:20]}, {"type": "text", "text": text[20:]}],
                        }
                    }
                ]
            },
        )
    )
    assert ask(server, photo).parameters["poissons_ratio"] == 0.45


def test_extract_json_object_rule():
    assert extract_json_object('{"a": 1}') == ({"a": 1}, False)
    assert extract_json_object('x {"a": {"b": [1, 2]}} y') == ({"a": {"b": [1, 2]}}, True)
    assert extract_json_object('{not json} {"a": 1}') == ({"a": 1}, True)
    with pytest.raises(ModelAnswerError, match="2 JSON objects"):
        extract_json_object('{"a": 1}\n{"b": 2}')
    with pytest.raises(ModelAnswerError, match="no JSON object"):
        extract_json_object('{"a": Infinity}')


@pytest.mark.parametrize(
    "url, shown",
    [
        ("https://user:sk-secret@api.example.com/v1", "https://***@api.example.com/v1"),
        ("https://sk-secret@api.example.com/v1", "https://***@api.example.com/v1"),
        ("https://api.example.com/v1?api-key=sk-secret", "https://api.example.com/v1?api-key=***"),
        ("https://api.example.com/v1?key=sk-secret&x=1", "https://api.example.com/v1?key=***&x=1"),
        ("https://api.example.com/v1?x=1&token=sk-secret", "https://api.example.com/v1?x=1&token=***"),
        ("http://localhost:11434/v1", "http://localhost:11434/v1"),
    ],
)
def test_redact_url_hides_credentials(url, shown):
    assert redact_url(url) == shown
    assert "sk-secret" not in repr(ModelConfig(url=url, model="m"))


@pytest.mark.parametrize("credentials", ["?api-key=sk-secret", "?key=sk-secret", "?token=sk-secret", "user:sk-secret@"])
def test_a_key_in_the_url_is_never_logged_or_shown(server, photo, caplog, credentials):
    caplog.set_level(logging.DEBUG)
    if credentials.endswith("@"):
        url = server.base_url.replace("://", "://" + credentials)
    else:
        url = server.base_url + credentials
    server.play(error(503, "busy"), error(401, "Incorrect API key provided: sk-secret"))
    with pytest.raises(ModelServiceError) as exc:
        query_material(photo[0], box=BOX, backend="openai", model_config=config(url, retries=1))
    assert "sk-secret" not in str(exc.value) and "***" in str(exc.value)
    assert "sk-secret" not in caplog.text
    with pytest.raises(InputError) as exc:
        chat_endpoint("ftp://" + credentials.rstrip("@").lstrip("?") + "@example.com/v1?api-key=sk-secret")
    assert "sk-secret" not in str(exc.value)


HTML_PAGE = b"""<!DOCTYPE html>
<html>
<head>
  <title>502 Bad Gateway</title>
  <style>body { font-family: sans-serif; }</style>
</head>
<body>
  <center><h1>502 Bad Gateway</h1></center>
  <hr><center>nginx/1.25.3</center>
  <p>The upstream server did not answer.</p>
  <p>Please try again later.</p>
</body>
</html>
"""


def test_an_html_error_page_is_one_line_with_its_status(server, photo):
    server.play(Reply(502, HTML_PAGE))
    with pytest.raises(ModelServiceError) as err:
        ask(server, photo, retries=0)
    message = str(err.value)
    assert "\n" not in message and "HTTP 502" in message and message.endswith("502 Bad Gateway")
    assert "<" not in message and "font-family" not in message


def test_credentials_in_the_endpoint_url_authenticate_and_stay_hidden(server, photo, caplog):
    """http://user:key@host/... connects to host with HTTP basic authentication (it used to
    fail as an unknown host "user:key@127.0.0.1")."""
    server.play(chat(answer()))
    url = server.base_url.replace("http://", "http://alice:s3cr%40t@")
    result = query_material(
        photo[0], box=BOX, backend="openai", model_config=ModelConfig(url=chat_endpoint(url), model="test-vision")
    )
    assert result.material == "elastic"
    sent = server.requests[-1].headers["Authorization"]
    assert sent == "Basic " + base64.b64encode(b"alice:s3cr@t").decode()
    assert "s3cr" not in caplog.text
