"""Foundation-model backend: ask an OpenAI-compatible chat-completions endpoint with an image.

Works with hosted models and local servers (Ollama, vLLM, llama.cpp) that accept
``image_url`` content parts. Standard library only (urllib). The question lists every
material type of the registry with its parameters, SI units and typical ranges, and asks
for one JSON object; the same description is sent as a ``json_schema`` response format.
A server that rejects ``response_format`` (HTTP 400/422) is asked again without it. The
answer is read by :mod:`clflow.query.answer`.
"""

from __future__ import annotations

import base64
import html
import http.client
import ipaddress
import json
import logging
import os
import re
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass, field

from clflow import __version__
from clflow.errors import ClflowError, InputError
from clflow.materials import DENSITY, MATERIALS, Param
from clflow.query.answer import ModelAnswerError, cross_check, extract_json_object, interpret_answer
from clflow.query.image import ImageFormat, ObjectImage
from clflow.query.knowledge import KnowledgeBase
from clflow.query.result import QueryResult, loads_strict

log = logging.getLogger("clflow.query")

URL_ENV = ("CLFLOW_LLM_URL", "OPENAI_BASE_URL")
MODEL_ENV = ("CLFLOW_LLM_MODEL",)
KEY_ENV = ("CLFLOW_LLM_API_KEY", "OPENAI_API_KEY")
RETRY_STATUS = frozenset({408, 429, 500, 502, 503, 504})
SCHEMA_REJECTED_STATUS = frozenset({400, 422})

# The knowledge base's convention (source "weakly-compressible" in materials_kb.json).
FLUID_CONVENTION = (
    "For fluids, bulk_modulus is the weakly compressible simulation value, about 1e5 to 1e6 Pa, "
    "not the physical bulk modulus (2.2e9 Pa for water). Unit [1] means dimensionless."
)

SYSTEM_PROMPT = (
    "You are a materials scientist who sets up physics simulations. You look at an object, "
    "name it, choose the closest simulated material type and estimate its density and "
    "material parameters in SI units. You answer with one JSON object and nothing else."
)


class ModelServiceError(ClflowError):
    """The model server is unreachable, timed out, refused the request or did not speak
    the chat-completions protocol."""


@dataclass(frozen=True)
class ModelConfig:
    """How to reach the model. ``url`` is the chat-completions endpoint; ``timeout`` (s)
    bounds the connection and each read; a failed attempt that may succeed later (no
    connection, timeout, HTTP 408/429/5xx) is retried ``retries`` times after
    ``backoff * 2**attempt`` seconds (or the server's Retry-After), at most ``max_backoff``."""

    url: str
    model: str
    api_key: str | None = field(default=None, repr=False)
    timeout: float = 60.0
    retries: int = 2
    backoff: float = 1.0
    max_backoff: float = 30.0
    image_format: ImageFormat = "png"
    structured_output: bool = True

    def __repr__(self) -> str:
        return f"ModelConfig(url={redact_url(self.url)!r}, model={self.model!r}, timeout={self.timeout!r})"

    def __post_init__(self):
        if not (self.timeout > 0 and self.retries >= 0 and self.backoff >= 0 and self.max_backoff >= 0):
            raise InputError("the model backend needs timeout > 0 s, retries >= 0, backoff >= 0 s")
        if self.image_format not in ("png", "jpeg"):
            raise InputError(f"image format {self.image_format!r} is not 'png' or 'jpeg'")

    @classmethod
    def resolve(
        cls, url: str | None = None, model: str | None = None, *, asked_by: str | None = None, **options
    ) -> "ModelConfig":
        """A config from arguments, else environment variables: the endpoint from
        ``--llm-url`` / $CLFLOW_LLM_URL / $OPENAI_BASE_URL (a base URL such as
        http://localhost:11434/v1 gets /chat/completions appended), the model from
        ``--model`` / $CLFLOW_LLM_MODEL, the key from $CLFLOW_LLM_API_KEY / $OPENAI_API_KEY.
        The key may be absent only for a server on this machine (loopback address).
        ``asked_by``: the config key that chose the backend, for a command without the options
        (the errors then name it and the environment variables only)."""

        def missing(what: str, option: str, env: str) -> InputError:
            way = f"set ${env}" if asked_by else f"pass {option} or set ${env}"
            return InputError(f"{asked_by or 'the openai backend'} needs {what}: {way}")

        given_by = "--llm-url"
        if not url:
            given_by, url = next(((f"${n}", os.environ[n]) for n in URL_ENV if os.environ.get(n)), (None, None))
        if not url:
            raise missing("an endpoint", "--llm-url", URL_ENV[0])
        model = model or _env(MODEL_ENV)
        if not model:
            raise missing("a model name", "--model", MODEL_ENV[0])
        endpoint = chat_endpoint(url, given_by)
        key = _env(KEY_ENV)
        if not key and not is_loopback(endpoint):
            raise InputError(
                f"no API key for {urllib.parse.urlsplit(endpoint).hostname}: set ${KEY_ENV[0]} "
                f"(or ${KEY_ENV[1]}); only a server on this machine may go without one"
            )
        return cls(url=endpoint, model=model, api_key=key, **options)


_SECRET_PARAMETER = re.compile(r"key|token|secret|password|passwd|auth|sig", re.IGNORECASE)


def redact_url(url: str) -> str:
    """``url`` for messages: user:password@ and the values of key/token-like query
    parameters (``?api-key=...``) replaced by ``***``."""
    try:
        parts = urllib.parse.urlsplit(url)
    except ValueError:
        return "***"
    netloc = parts.netloc
    if "@" in netloc:
        netloc = "***@" + netloc.rpartition("@")[2]
    query = "&".join(_redact_parameter(p) for p in parts.query.split("&")) if parts.query else ""
    return urllib.parse.urlunsplit((parts.scheme, netloc, parts.path, query, parts.fragment))


def _redact_parameter(parameter: str) -> str:
    name, equals, value = parameter.partition("=")
    return f"{name}=***" if equals and value and _SECRET_PARAMETER.search(name) else parameter


def _url_secrets(url: str) -> list[str]:
    """The credentials written into ``url`` (its userinfo and its password, as written and
    decoded; key/token query values), longest first."""
    try:
        parts = urllib.parse.urlsplit(url)
    except ValueError:
        return [url]
    secrets = []
    if "@" in parts.netloc:
        userinfo = parts.netloc.rpartition("@")[0]
        password = userinfo.partition(":")[2]
        secrets += [userinfo, password, urllib.parse.unquote(password)]
    secrets += [p.partition("=")[2] for p in parts.query.split("&") if _redact_parameter(p) != p]
    return sorted({s for s in secrets if s}, key=len, reverse=True)


def _env(names: tuple[str, ...]) -> str | None:
    return next((os.environ[n] for n in names if os.environ.get(n)), None)


def chat_endpoint(url: str, given_by: str = "--llm-url") -> str:
    """The chat-completions URL of ``url`` (an endpoint or an OpenAI-style base URL;
    ``given_by``: the option or environment variable that gave it, for the errors)."""
    parts = urllib.parse.urlsplit(url.strip())
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise InputError(f"{given_by} {redact_url(url)!r} is not an http(s) URL such as http://localhost:11434/v1")
    try:
        port = parts.port  # None when not given
    except ValueError:  # out of range or not a number: a wrong URL, not a server that refuses the connection
        port = 0
    if port == 0:
        raise InputError(f"{given_by} {redact_url(url)!r}: the port must be a number from 1 to 65535")
    path = parts.path.rstrip("/")
    if not path.endswith("/chat/completions"):
        path += "/chat/completions"
    return urllib.parse.urlunsplit((parts.scheme, parts.netloc, path, parts.query, ""))


def is_loopback(url: str) -> bool:
    host = urllib.parse.urlsplit(url).hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# --------------------------------------------------------------------------- the question


def answer_schema() -> dict:
    """JSON schema of the answer, built from the registry (strict-mode compatible: every
    object closed, every property required)."""

    def quantity(p: Param) -> dict:
        lo, hi = p.typical
        about = f"{p.doc or p.name} ({p.symbol}), typically {lo:g} to {hi:g} {p.unit}"
        return _closed(
            {"value": {"type": "number", "description": about}, "unit": {"type": "string", "enum": [p.unit]}}
        )

    variants = [
        {**_closed({p.name: quantity(p) for p in m.params}), "description": f"parameters of {m.name}: {m.model}"}
        for m in MATERIALS.values()
    ]
    return _closed(
        {
            "object": {"type": "string", "description": "what the object is, in a few words"},
            "material": {"type": "string", "enum": list(MATERIALS), "description": "closest material type"},
            "density": quantity(DENSITY),
            "parameters": {"anyOf": variants, "description": "every parameter of the chosen material type"},
            "confidence": {"type": "number", "description": "how sure you are, 0 to 1"},
            "reasoning": {"type": "string", "description": "one or two sentences"},
        }
    )


def _closed(properties: dict) -> dict:
    return {"type": "object", "properties": properties, "required": list(properties), "additionalProperties": False}


def question(prompt: str = "", object_name: str = "") -> str:
    """The user message: the task, the material types with parameters and units, the format."""
    lines = ["Look at the object in the image."]
    if object_name:
        lines.append(f"The object is: {object_name}.")
    if prompt:
        lines.append(f"The user says: {prompt}")
    lines += [
        "Decide what the object is and which of these material types describes how it deforms "
        "and flows, then estimate its density and every parameter of that type, in exactly "
        "these SI units (units in brackets, typical ranges in parentheses):",
        f"- density [{DENSITY.unit}] ({DENSITY.typical[0]:g} to {DENSITY.typical[1]:g})",
    ]
    for m in MATERIALS.values():
        params = "; ".join(f"{p.name} ({p.symbol}) [{p.unit}] ({p.typical[0]:g} to {p.typical[1]:g})" for p in m.params)
        lines.append(f"- {m.name}: {m.model}. Parameters: {params}")
    lines.append(FLUID_CONVENTION)
    lines.append(
        'Answer with one JSON object only: {"object": "...", "material": "<type>", '
        f'"density": {{"value": <number>, "unit": "{DENSITY.unit}"}}, "parameters": {{"<name>": '
        '{"value": <number>, "unit": "<unit>"}, ...}, "confidence": <0 to 1>, "reasoning": "..."}'
    )
    return "\n".join(lines)


def request_body(config: ModelConfig, text: str, image: ObjectImage, structured: bool) -> dict:
    body = {
        "model": config.model,
        "temperature": 0,
        "messages": [
            {"role": "system", "content": SYSTEM_PROMPT},
            {
                "role": "user",
                "content": [
                    {"type": "text", "text": text},
                    {"type": "image_url", "image_url": {"url": image.data_url(config.image_format)}},
                ],
            },
        ],
    }
    if structured:
        body["response_format"] = {
            "type": "json_schema",
            "json_schema": {"name": "material_query", "strict": True, "schema": answer_schema()},
        }
    return body


# --------------------------------------------------------------------------- HTTP


class _Failure(Exception):
    """One failed attempt: ``status`` (None for no HTTP answer), a message, Retry-After (s)."""

    def __init__(self, status: int | None, message: str, retry_after: float | None = None):
        super().__init__(message)
        self.status, self.message, self.retry_after = status, message, retry_after

    @property
    def retryable(self) -> bool:
        return self.status is None or self.status in RETRY_STATUS


def _without_credentials(url: str) -> tuple[str, str | None]:
    """(``url`` without its user:password@, the HTTP basic Authorization header they make or
    None): urllib would take them for part of the host name."""
    parts = urllib.parse.urlsplit(url)
    if "@" not in parts.netloc:
        return url, None
    userinfo, _, host = parts.netloc.rpartition("@")
    user, _, password = userinfo.partition(":")
    token = base64.b64encode(f"{urllib.parse.unquote(user)}:{urllib.parse.unquote(password)}".encode()).decode()
    return urllib.parse.urlunsplit(parts._replace(netloc=host)), f"Basic {token}"


def _post_once(config: ModelConfig, payload: bytes) -> bytes:
    headers = {"Content-Type": "application/json", "Accept": "application/json", "User-Agent": f"clflow/{__version__}"}
    url, basic = _without_credentials(config.url)
    if config.api_key:
        headers["Authorization"] = f"Bearer {config.api_key}"
    elif basic:
        headers["Authorization"] = basic
    req = urllib.request.Request(url, data=payload, headers=headers, method="POST")
    # A server on this machine is never reached through a proxy ($http_proxy etc.).
    proxies = {} if is_loopback(config.url) else None
    opener = urllib.request.build_opener(urllib.request.ProxyHandler(proxies))
    try:
        with opener.open(req, timeout=config.timeout) as resp:
            return resp.read()
    except urllib.error.HTTPError as exc:
        message = f"HTTP {exc.code} {exc.reason}: {_error_text(exc)}"
        raise _Failure(exc.code, message, _retry_after(exc.headers)) from None
    except urllib.error.URLError as exc:
        raise _Failure(None, _reason(exc.reason, config.timeout)) from None
    except (OSError, http.client.HTTPException) as exc:
        raise _Failure(None, _reason(exc, config.timeout)) from None


def _reason(reason: object, timeout: float) -> str:
    if isinstance(reason, ConnectionRefusedError):
        return "connection refused (is the server running?)"
    if isinstance(reason, (TimeoutError, socket.timeout)):
        return f"no answer within the {timeout:g} s timeout"
    if isinstance(reason, socket.gaierror):
        return f"unknown host ({reason.strerror})"
    return str(reason) or type(reason).__name__


ERROR_TEXT_CHARS = 200  # of an error body that is not the API's JSON (an HTML page, say)


def _error_text(exc: urllib.error.HTTPError) -> str:
    """One line from an error response: the API's JSON message, else an HTML page's title
    (or its text), else the body's first characters."""
    body = exc.read()[:20000].decode("utf-8", "replace")
    try:
        err = json.loads(body)["error"]
        text = str(err.get("message", err)) if isinstance(err, dict) else str(err)
    except (ValueError, KeyError, TypeError):
        title = re.search(r"<title[^>]*>(.*?)</title>", body, re.I | re.S)
        text = title.group(1) if title else re.sub(r"<[^>]+>", " ", body)
    text = " ".join(html.unescape(text).split())
    return (text[: ERROR_TEXT_CHARS - 3] + "...") if len(text) > ERROR_TEXT_CHARS else (text or "(no message)")


def _retry_after(headers) -> float | None:
    try:
        return max(0.0, float(headers.get("Retry-After")))
    except (TypeError, ValueError):
        return None


def _post(config: ModelConfig, body: dict) -> bytes:
    """POST ``body`` with retries; the response body, or :class:`ModelServiceError` (a
    rejected ``response_format`` is re-raised as :class:`_Failure` for the caller)."""
    payload = json.dumps(body).encode()
    attempts = config.retries + 1
    attempt = 0
    while True:
        try:
            return _post_once(config, payload)
        except _Failure as failure:
            if "response_format" in body and failure.status in SCHEMA_REJECTED_STATUS:
                raise
            attempt += 1
            if not failure.retryable or attempt == attempts:
                raise _service_error(config, failure, attempt) from None
            delay = config.backoff * 2 ** (attempt - 1) if failure.retry_after is None else failure.retry_after
            delay = min(config.max_backoff, delay)
            log.warning(
                _redact(
                    f"{config.url}: {failure.message}; retrying in {delay:.3g} s ({attempt + 1}/{attempts})", config
                )
            )
            time.sleep(delay)


def _service_error(config: ModelConfig, failure: _Failure, attempts: int) -> ModelServiceError:
    verb = "refused the request" if failure.status else "could not be reached"
    tried = f" after {attempts} attempts" if attempts > 1 else ""
    hint = {401: " (check the API key)", 403: " (check the API key)", 404: " (check --llm-url and --model)"}
    message = f"model server {config.url} {verb}{tried}: {failure.message}{hint.get(failure.status, '')}"
    return ModelServiceError(_redact(message, config))


def _redact(text: str, config: ModelConfig) -> str:
    """``text`` without the API key and the credentials in the endpoint URL."""
    text = text.replace(config.url, redact_url(config.url))
    for secret in [config.api_key, *_url_secrets(config.url)]:
        if secret:
            text = text.replace(secret, "***")
    return text


def _message_text(raw: bytes, config: ModelConfig) -> str:
    """The assistant's text of a chat-completions response."""
    try:
        envelope = loads_strict(raw)
        message = envelope["choices"][0]["message"]
        if not isinstance(message, dict):
            raise TypeError("message is not an object")
    except (ValueError, KeyError, IndexError, TypeError):
        excerpt = raw[:300].decode("utf-8", "replace")
        message = f"{config.url} did not answer as a chat-completions server: {excerpt!r}"
        raise ModelServiceError(_redact(message, config)) from None
    if message.get("refusal"):
        raise ModelAnswerError(_redact(f"the model refused to answer: {message['refusal']}", config))
    content = message.get("content")
    if isinstance(content, list):  # some servers answer in content parts
        content = "".join(part.get("text", "") for part in content if isinstance(part, dict))
    if not isinstance(content, str) or not content.strip():
        reason = envelope["choices"][0].get("finish_reason")
        raise ModelAnswerError(f"the model's answer is empty (finish_reason: {reason})")
    return content


def query_model(
    image: ObjectImage,
    config: ModelConfig,
    kb: KnowledgeBase,
    prompt: str = "",
    object_name: str = "",
) -> QueryResult:
    """Ask the model about the object in ``image``; the validated :class:`QueryResult`."""
    text = question(prompt, object_name)
    h, w = image.pixels.shape[:2]
    log.info("asking %s at %s about a %dx%d px crop of %s", config.model, redact_url(config.url), w, h, image.source)
    warnings: list[str] = []
    structured = config.structured_output
    try:
        raw = _post(config, request_body(config, text, image, structured))
    except _Failure as failure:
        warnings.append(
            _redact(
                f"the server rejected the json_schema response format ({failure.message}); "
                "asked for JSON in the prompt instead",
                config,
            )
        )
        structured = False
        raw = _post(config, request_body(config, text, image, structured))
    content = _redact(_message_text(raw, config), config)
    answer, surrounded = extract_json_object(content)
    if surrounded:
        warnings.append("text around the JSON answer was ignored")
    fields = interpret_answer(answer, kb)
    matched = cross_check(fields, kb)
    fields["warnings"] = warnings + fields["warnings"]  # the caller shows them, once
    return QueryResult(
        **fields,
        backend="openai",
        model=config.model,
        prompt=text,
        raw_answer=content,
        matched=matched,
        image=image.source,
        crop_box=list(image.box),
        structured_output=structured,
    )
